"""``omnirecon inspect``: validate a scene, print a summary, draw cameras and epipolar lines."""

from __future__ import annotations

from omnirecon.outputs import prepare_out
from omnirecon.workflows.inspect import InspectConfig, run_inspect


class InspectCommand(InspectConfig):
    __doc__ = InspectConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        prepare_out(self.out)  # writable, stale temporaries gone: before any work
        run_inspect(self)
