"""``omnirecon edit``: recolour or remove an object consistently in novel views; edit its mesh faces."""

from __future__ import annotations

from omnirecon.workflows.edit import EditConfig


class EditCommand(EditConfig):
    __doc__ = EditConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        for line in self.run_claimed():  # --out built beside, swapped in whole: see workflows/folder.py
            print(line)
