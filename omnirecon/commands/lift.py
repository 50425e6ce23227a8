"""``omnirecon lift``: lift a 2-D predictor into novel views with a model's blend weights (predict-then-blend)."""

from __future__ import annotations

from omnirecon.outputs import prepare_out
from omnirecon.workflows.lift import LiftConfig


class LiftCommand(LiftConfig):
    __doc__ = LiftConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        prepare_out(self.out)  # writable, stale temporaries gone: before any work
        for line in self.run():
            print(line)
