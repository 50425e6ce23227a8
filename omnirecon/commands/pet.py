"""``omnirecon pet``: parameter-efficient tuning of Omni-Recon's appearance branch on lifted labels."""

from __future__ import annotations

from omnirecon.workflows.pet import PETConfig


class PETCommand(PETConfig):
    __doc__ = PETConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        for line in self.run_claimed():  # --out built beside, swapped in whole: see workflows/folder.py
            print(line)
