"""``omnirecon mesh``: a mesh from a model's rendered depth (TSDF fusion), in the input frame."""

from __future__ import annotations

from omnirecon.outputs import prepare_out
from omnirecon.workflows.mesh import MeshConfig, run_mesh, summary_lines


class MeshCommand(MeshConfig):
    __doc__ = MeshConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        prepare_out(*self.out, kind="file")  # writable, stale temporaries gone: before any work
        result = run_mesh(self)
        for p in result["files"]:
            print(f"wrote {p}")
        for line in summary_lines(result):
            print(line)
