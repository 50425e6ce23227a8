"""``omnirecon lift``: lift a 2-D predictor into novel views with a model's blend weights (predict-then-blend)."""

from __future__ import annotations

from omnirecon.outputs import claim
from omnirecon.workflows.lift import LiftConfig


class LiftCommand(LiftConfig):
    __doc__ = LiftConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        with claim(self.out, "lift", inputs=(self.ckpt, self.scene, self.user_model)):  # checked, locked, marked: see outputs.claim
            lines = self.run()
        for line in lines:
            print(line)
