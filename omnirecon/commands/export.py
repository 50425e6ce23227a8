"""``omnirecon export``: a mesh with baked vertex colours (PLY, GLB) and a static web-viewer bundle."""

from __future__ import annotations

from dataclasses import replace

from omnirecon.outputs import claim, relative_to
from omnirecon.workflows.export import ExportConfig, default_out, run_export


class ExportCommand(ExportConfig):
    __doc__ = ExportConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        out = default_out(self)
        # mesh.ply, mesh.glb, export.json and viewer/ are one set: built beside --out, swapped in whole.
        with claim(out, "export", inputs=(self.ckpt, self.scene, self.mesh, self.finetune), mode="replace") as c:
            record = relative_to(run_export(replace(self, out=c.work)), c.work)
        for p in record["files"]:
            print(f"wrote {out / p}")
        b = record["bake"]
        print(f"{record['vertices']:,} vertices, {record['faces']:,} faces; baked from {b['mean_views']:.2f} views per "
              f"vertex on average ({b['fallback']} fallback, {b['unseen']} unseen)")
        if self.viewer:
            print(f"view it: omnirecon view {out}")
