"""``omnirecon demo``: novel views, scores and a mesh of one scene with the shipped checkpoints, as an
HTML report."""

from __future__ import annotations

from omnirecon.outputs import claim
from omnirecon.workflows.demo import DemoConfig, run_demo


class DemoCommand(DemoConfig):
    __doc__ = DemoConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        with claim(self.out, "demo", inputs=(self.data, self.checkpoints), recursive=True):  # see outputs.claim
            result = run_demo(self)
        for line in result["lines"]:
            print(line)
        print(f"report: {result['report']}")
