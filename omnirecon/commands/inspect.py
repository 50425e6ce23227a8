"""``omnirecon inspect``: validate a scene, print a summary, draw cameras and epipolar lines."""

from __future__ import annotations

from omnirecon.outputs import claim
from omnirecon.workflows.inspect import InspectConfig, run_inspect


class InspectCommand(InspectConfig):
    __doc__ = InspectConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        with claim(self.out, "inspect", inputs=(self.path,)):  # checked, locked, marked: see outputs.claim
            run_inspect(self)
