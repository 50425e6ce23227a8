"""``omnirecon pet``: parameter-efficient tuning of Omni-Recon's appearance branch on lifted labels."""

from __future__ import annotations

from omnirecon.outputs import prepare_out
from omnirecon.workflows.pet import PETConfig


class PETCommand(PETConfig):
    __doc__ = PETConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        prepare_out(self.out)  # writable, stale temporaries gone: before any work
        for line in self.run():
            print(line)
