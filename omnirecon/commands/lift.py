"""``omnirecon lift``: lift a 2-D predictor into novel views with a model's blend weights (predict-then-blend)."""

from __future__ import annotations

from omnirecon.workflows.lift import LiftConfig


class LiftCommand(LiftConfig):
    __doc__ = LiftConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        for line in self.run_claimed():  # --out built beside, swapped in whole: see workflows/folder.py
            print(line)
