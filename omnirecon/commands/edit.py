"""``omnirecon edit``: recolour or remove an object consistently in novel views; edit its mesh faces."""

from __future__ import annotations

from omnirecon.outputs import claim
from omnirecon.workflows.edit import EditConfig


class EditCommand(EditConfig):
    __doc__ = EditConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        with claim(self.out, "edit", inputs=(self.ckpt, self.scene)):  # checked, locked, marked: see outputs.claim
            lines = self.run()
        for line in lines:
            print(line)
