"""``omnirecon inspect``: validate a scene, print a summary, draw cameras and epipolar lines."""

from __future__ import annotations

from omnirecon.workflows.inspect import InspectConfig, run_inspect


class InspectCommand(InspectConfig):
    __doc__ = InspectConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        run_inspect(self)
