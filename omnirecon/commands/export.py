"""``omnirecon export``: a mesh with baked vertex colours (PLY, GLB) and a static web-viewer bundle."""

from __future__ import annotations

from omnirecon.outputs import claim
from omnirecon.workflows.export import ExportConfig, run_export


class ExportCommand(ExportConfig):
    __doc__ = ExportConfig.__doc__  # the options' description is the command's help

    def main(self) -> None:
        with claim(self.out, "export", inputs=(self.ckpt, self.scene, self.mesh)):  # see outputs.claim
            record = run_export(self)
        for p in record["files"]:
            print(f"wrote {p}")
        b = record["bake"]
        print(f"{record['vertices']:,} vertices, {record['faces']:,} faces; baked from {b['mean_views']:.2f} views per "
              f"vertex on average ({b['fallback']} fallback, {b['unseen']} unseen)")
        if self.viewer:
            print(f"view it: omnirecon view {record['out']}")
