"""What ``omnirecon export`` does, as a function of its options: read the scene and model, mesh it (or
take ``--mesh``), bake vertex colours and write the viewer bundle (:func:`omnirecon.viewer.export.export_scene`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from omnirecon.data import detect_format
from omnirecon.engine.machine import MachineConfig, load_model, pick_device, set_threads
from omnirecon.engine.protocols import protocol_for
from omnirecon.engine.scenes import load_at_resolution
from omnirecon.engine.views import check_views, default_views
from omnirecon.mesh.build import MeshOptions
from omnirecon.mesh.files import read_mesh
from omnirecon.mesh.ibr import scene_defaults
from omnirecon.options import check_options
from omnirecon.progress import progress_bar
from omnirecon.viewer.export import ExportOptions, export_scene


@dataclass
class ExportConfig(MachineConfig):
    """Export a mesh with baked vertex colours (PLY and GLB, input frame) and a static web viewer that
    renders it in real time with the model's image-based shading in a WebGL2 shader (`omnirecon view`)."""

    scene: Path
    """Scene folder (any supported format); read at its eval-protocol resolution, normalised."""
    ckpt: Path
    """Checkpoint folder of an Omni-Recon model (`omnirecon train --model omnirecon-*`)."""
    views: tuple[int, ...] | None = None
    """Source view indices (default: 23 24 33 on DTU, else --num-views evenly spaced train views)."""
    num_views: int = 3
    """Source views K when --views is not given."""
    mesh: Path | None = None
    """Mesh file in the input frame (e.g. from `omnirecon mesh`); default: mesh the scene with the model."""
    out: Path | None = None
    """Output folder (default: outputs/export/<scene>)."""
    resolution: int | None = None
    """Long side of the source images in pixels (default: the scene's eval protocol, 128)."""
    bake_views: int = 3
    """Most frontal visible source views blended per vertex for the baked colours."""
    visibility: bool = True
    """The viewer starts with the per-source occlusion test on (toggle it in the viewer)."""
    visibility_tol: float = 0.01
    """Relative depth tolerance of the occlusion test."""
    viewer: bool = True
    """Write the viewer bundle (needs three.js: `npm install` in omnirecon/viewer, done by `make setup`)."""
    max_edge: float = 0.0
    """Subdivide triangles until no edge exceeds this fraction of the bounds diagonal before baking, so
    the vertex colours can carry the texture of large triangles (0: keep the mesh; e.g. 0.005)."""
    voxel: float = 1 / 256
    """Without --mesh: TSDF voxel size as a fraction of the bounds diagonal."""
    masks: bool = True
    """Without --mesh: clean the mesh with the source views' object masks when the scene has them."""
    background: Literal["white", "black"] = "white"
    """Colour RGBA inputs are composited on."""
    blend: Literal["auto", "network", "angle"] = "auto"
    """The blend the viewer starts with (it can switch): `network`, the appearance branch's weights; `angle`, each
    point's --angle-sources nearest sources by viewing angle (as `finetune --blend angle`); `auto`, per scene kind
    as `finetune` (angle on real object captures with masks such as DTU, else network)."""
    angle_sources: int = 4
    """Sources per point of the angle blend (0: every source that sees it): what `finetune --angle-sources 3 4 6 8`
    chose on its validation views on the DTU scans (`reconstruct` passes its own finetune's choice)."""


def default_out(cfg: ExportConfig) -> Path:
    """``--out``, or ``outputs/export/<scene>``."""
    return cfg.out or Path("outputs/export") / Path(cfg.scene).name


def run_export(cfg: ExportConfig, mesh=None) -> dict:
    """Run ``omnirecon export``; returns :func:`export_scene`'s record (plus ``out``). ``mesh``: a
    ``trimesh.Trimesh`` in the input frame handed over in memory (``reconstruct``), instead of ``cfg.mesh``."""

    options = ExportOptions(cfg.bake_views, cfg.visibility, cfg.visibility_tol, cfg.viewer, max_edge=cfg.max_edge,
                            blend="network" if cfg.blend == "auto" else cfg.blend, angle_sources=cfg.angle_sources)
    options.check()
    check_options("export", cfg)  # the numbers (omnirecon/options.py); here for callers other than the CLI
    if mesh is None and cfg.mesh is not None:
        mesh = read_mesh(cfg.mesh)
    set_threads(cfg.threads)
    device = pick_device(cfg.device)
    fmt = detect_format(cfg.scene)
    net, info = load_model(cfg.ckpt, None, device)
    proto = protocol_for(Path(cfg.scene), fmt)
    scene = load_at_resolution(cfg.scene, cfg.resolution or proto.long_side, cfg.background, fmt)
    views = check_views(cfg.views, len(scene), cfg.scene) if cfg.views else default_views(scene, cfg.num_views)
    if cfg.blend == "auto":
        options.blend = scene_defaults(scene)[0]
    out = default_out(cfg)
    mesh_options = MeshOptions(voxel=cfg.voxel, chunk=cfg.chunk)
    if mesh is None:
        mesh_options.check()
    if mesh is None:
        with progress_bar() as bar:
            record = export_scene(net, scene, views, out, None, mesh_options, options, device, info, cfg.masks, bar)
    else:
        record = export_scene(net, scene, views, out, mesh, mesh_options, options, device, info, cfg.masks)
    record["out"] = str(out)
    return record
