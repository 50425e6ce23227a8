"""``omnirecon pet``: parameter-efficient tuning of Omni-Recon's appearance branch on lifted labels."""

from __future__ import annotations

from omnirecon.outputs import claim
from omnirecon.workflows.pet import PETConfig


class PETCommand(PETConfig):
    __doc__ = PETConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        with claim(self.out, "pet", inputs=(self.ckpt, self.scene)):  # checked, locked, marked: see outputs.claim
            lines = self.run()
        for line in lines:
            print(line)
