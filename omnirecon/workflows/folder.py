"""Verbs whose output is one folder of their own (``lift``, ``edit``, ``pet``): how they take their ``--out``.

A config mixes in :class:`FolderVerb`, names its folder when ``--out`` is not given (``default_out``) and
writes everything into the ``folder`` its ``run(folder)`` is given; :meth:`FolderVerb.run_claimed` (what the
command calls) takes ``--out`` with :func:`omnirecon.outputs.claim`: checked, locked against a second run,
built in a temporary twin beside it and swapped in whole at the end, so an interrupt leaves the previous
folder or the complete new one. The lines ``run`` returns name ``--out``, never the twin. Called as a
library (``LiftConfig(...).run()``, e.g. by the demo), ``run`` writes into ``--out`` directly.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

from omnirecon.options import SourceOcclusion
from omnirecon.outputs import claim


class FolderVerb:
    """Mixin for the config of a verb that writes one folder (see the module docstring)."""

    command: ClassVar[str]
    """The verb's name (recorded in the folder's marker)."""

    def default_out(self) -> Path:
        """The output folder when --out is not given."""
        raise NotImplementedError

    def inputs(self) -> tuple:
        """The paths the run reads (--out may neither be nor hold nor lie inside one)."""
        return self.ckpt, self.scene

    def run(self, folder: Path | None = None) -> list[str]:
        """Write the outputs into ``folder`` (default: --out); returns the lines to print, naming --out."""
        raise NotImplementedError

    def run_claimed(self) -> list[str]:
        """``run`` into the temporary twin of --out, swapped in when it succeeds; returns the lines to print."""
        with claim(self.out or self.default_out(), self.command, inputs=self.inputs(), mode="replace") as c:
            return self.run(c.work)


@dataclass(kw_only=True)
class LiftedTargets(SourceOcclusion):
    """The options of ``lift`` and ``edit``: which targets, and the path their sources' signals are blended by."""

    targets: tuple[int, ...] = ()
    """Target view indices (default: the protocol's targets)."""
    path: Literal["volumetric", "mesh"] = "volumetric"
    """volumetric: blend with the model's ray weights; mesh: one surface point per pixel of a mesh (Omni-Recon only;
    lift's render-then-predict baseline then runs on the mesh path's render)."""
    mesh: str = "auto"
    """--path mesh (and edit's mesh edit): gt (a procedural scene's exact mesh), model (baked from the model's depth at
    the targets' sources, `omnirecon mesh`'s protocol), auto (gt if any, else model) or a mesh file in the scene's
    input frame."""
