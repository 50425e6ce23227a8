"""``omnirecon mesh``: a mesh from a model's rendered depth (TSDF fusion), in the input frame."""

from __future__ import annotations

from pathlib import Path

from omnirecon.outputs import claim
from omnirecon.workflows.mesh import MeshConfig, run_mesh, set_files, summary_lines


class MeshCommand(MeshConfig):
    __doc__ = MeshConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        first = self.out[0] if self.out else Path("outputs/mesh") / Path(self.scene).name
        inputs = (self.scene, self.ckpt)
        # Every file of the set (meshes, metrics, preview) locked, and refused when a user's (without
        # --overwrite); the set is written whole by run_mesh.
        files = set_files(self) if self.out else ()
        with claim(first, "mesh", inputs=inputs, mode="file", overwrite=self.overwrite, files=files):
            result = run_mesh(self)
        for p in result["files"]:
            print(f"wrote {p}")
        for line in summary_lines(result):
            print(line)
