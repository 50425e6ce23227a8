"""``omnirecon demo``: novel views, scores and a mesh of one scene with the shipped checkpoints, as an
HTML report."""

from __future__ import annotations

from omnirecon.outputs import prepare_out
from omnirecon.workflows.demo import DemoConfig, run_demo


class DemoCommand(DemoConfig):
    __doc__ = DemoConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        prepare_out(self.out, recursive=True)  # writable, stale temporaries gone: before any work
        result = run_demo(self)
        for line in result["lines"]:
            print(line)
        print(f"report: {result['report']}")
