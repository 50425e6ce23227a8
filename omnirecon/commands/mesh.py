"""``omnirecon mesh``: a mesh from a model's rendered depth (TSDF fusion), in the input frame."""

from __future__ import annotations

from pathlib import Path

from omnirecon.outputs import check_out, claim
from omnirecon.workflows.mesh import MeshConfig, run_mesh, summary_lines


class MeshCommand(MeshConfig):
    __doc__ = MeshConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        first = self.out[0] if self.out else Path("outputs/mesh") / Path(self.scene).name
        inputs = (self.scene, self.ckpt)
        # One run per mesh set; the set (meshes, metrics, preview) is written whole by run_mesh.
        with claim(first, "mesh", inputs=inputs, mode="file"):
            for extra in self.out[1:]:
                check_out(extra, "file", inputs)
            result = run_mesh(self)
        for p in result["files"]:
            print(f"wrote {p}")
        for line in summary_lines(result):
            print(line)
