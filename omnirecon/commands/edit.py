"""``omnirecon edit``: recolour or remove an object consistently in novel views; edit its mesh faces."""

from __future__ import annotations

from omnirecon.outputs import prepare_out
from omnirecon.workflows.edit import EditConfig


class EditCommand(EditConfig):
    __doc__ = EditConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        prepare_out(self.out)  # writable, stale temporaries gone: before any work
        for line in self.run():
            print(line)
