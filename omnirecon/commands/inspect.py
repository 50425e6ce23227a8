"""``omnirecon inspect``: validate a scene, print a summary, draw cameras and epipolar lines."""

from __future__ import annotations

from omnirecon.outputs import claim
from omnirecon.workflows.inspect import InspectConfig, default_out, run_inspect


class InspectCommand(InspectConfig):
    __doc__ = InspectConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        out = self.out or default_out(self)
        # The output set is built beside --out and swapped in whole (see outputs.claim).
        with claim(out, "inspect", inputs=(self.path,), mode="replace") as c:
            run_inspect(self, c.work)
