"""``omnirecon demo``: novel views, scores and a mesh of one scene with the shipped checkpoints, as an
HTML report."""

from __future__ import annotations

from dataclasses import replace

from omnirecon.outputs import claim
from omnirecon.workflows.demo import DemoConfig, run_demo


class DemoCommand(DemoConfig):
    __doc__ = DemoConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        # The output set is built beside --out and swapped in whole (see outputs.claim).
        with claim(self.out, "demo", inputs=(self.data, self.checkpoints), mode="replace") as c:
            result = run_demo(replace(self, out=c.work))
        for line in [*result["lines"], f"report: {result['report']}"]:
            print(line.replace(str(c.work), str(self.out)))  # the lines name the folder the run was built in
