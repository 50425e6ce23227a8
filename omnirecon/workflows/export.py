"""What ``omnirecon export`` does, as a function of its options: read the scene and model, mesh it (or
take ``--mesh``), bake vertex colours and write the viewer bundle (:func:`omnirecon.viewer.export.export_scene`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from omnirecon.data import detect_format
from omnirecon.engine.machine import CheckpointInput, MachineConfig, load_model, pick_device, set_threads
from omnirecon.engine.protocols import protocol_for
from omnirecon.engine.scenes import load_at_resolution
from omnirecon.engine.views import check_views, default_views
from omnirecon.errors import InputError
from omnirecon.mesh.build import MeshOptions
from omnirecon.mesh.files import read_mesh
from omnirecon.options import (
    MeshBlend,
    MeshFile,
    Meshing,
    OutFolder,
    PhotoSize,
    SceneInput,
    ViewerBundle,
    check_options,
    command_defaults,
)
from omnirecon.progress import progress_bar
from omnirecon.viewer.export import ExportOptions, export_scene


@dataclass
@command_defaults(voxel=1 / 256, masks=True)
class ExportConfig(OutFolder, CheckpointInput, SceneInput, MeshFile, PhotoSize, Meshing, MeshBlend, ViewerBundle,
                   MachineConfig):
    """Export a mesh with baked vertex colours (PLY and GLB, input frame) and a static web viewer that
    renders it in real time with the model's image-based shading in a WebGL2 shader (`omnirecon view`)."""

    num_views: int | None = None
    """With neither --views nor --finetune: this many evenly spaced train views instead of all of them."""
    finetune: Path | None = None
    """An `omnirecon finetune` output folder (or its curve.json): the viewer starts with what it scored (its "render"
    record: blend, fill, sources per frame, angle sources, source masks, cracks) over its sources."""
    bake_views: int = 3
    """Most frontal visible source views blended per vertex for the baked colours."""
    visibility_tol: float = 0.01
    """Relative depth tolerance of the occlusion test."""
    max_edge: float = 0.0
    """Subdivide triangles until no edge exceeds this fraction of the bounds diagonal before baking, so
    the vertex colours can carry the texture of large triangles (0: keep the mesh; e.g. 0.005)."""
    background: Literal["white", "black"] = "white"
    """Colour RGBA inputs are composited on."""
    angle_sources: int | None = None
    """Sources per point of the angle blend (0: every source that sees it; default: --finetune's, else 4, what
    `finetune --angle-sources 3 4 6 8` chose on its validation views on the DTU scans)."""
    cracks: int | None = None
    """The crack fill's radius in pixels (0: off; default: --finetune's, else 2)."""


def default_out(cfg: ExportConfig) -> Path:
    """``--out``, or ``outputs/export/<scene>``."""
    return cfg.out or Path("outputs/export") / Path(cfg.scene).name


def run_export(cfg: ExportConfig, mesh=None) -> dict:
    """Run ``omnirecon export``; returns :func:`export_scene`'s record (plus ``out``). ``mesh``: a
    ``trimesh.Trimesh`` in the input frame handed over in memory (``reconstruct``), instead of ``cfg.mesh``."""

    auto = lambda v: None if v == "auto" else v  # noqa: E731
    options = ExportOptions(cfg.bake_views, cfg.visibility, cfg.visibility_tol, cfg.viewer, max_edge=cfg.max_edge,
                            blend=auto(cfg.blend), angle_sources=cfg.angle_sources, fill=auto(cfg.fill),
                            cracks=cfg.cracks)
    options.check()
    check_options("export", cfg)  # the numbers (omnirecon/options.py); here for callers other than the CLI
    record = read_record(cfg.finetune) if cfg.finetune is not None else None
    if mesh is None and cfg.mesh is not None:
        mesh = read_mesh(cfg.mesh)
    set_threads(cfg.threads)
    device = pick_device(cfg.device)
    fmt = detect_format(cfg.scene)
    net, info = load_model(cfg.ckpt, None, device)
    proto = protocol_for(Path(cfg.scene), fmt)
    scored = max(record["resolution"]) if record and record.get("resolution") else None  # what finetune scored at
    scene = load_at_resolution(cfg.scene, cfg.resolution or scored or proto.long_side, cfg.background, fmt)
    views = bundle_views(cfg, scene, record)
    out = default_out(cfg)
    mesh_options = MeshOptions(voxel=cfg.voxel, chunk=cfg.chunk)
    if mesh is None:
        mesh_options.check()
    if mesh is None:  # meshed from the given views, else from 3 (the model's depth at every view is slow)
        mesh_views = views if cfg.views or cfg.num_views else default_views(scene, 3)
        with progress_bar() as bar:
            done = export_scene(net, scene, views, out, None, mesh_options, options, device, info, cfg.masks, bar, record,
                                mesh_views)
    else:
        done = export_scene(net, scene, views, out, mesh, mesh_options, options, device, info, cfg.masks, None, record)
    done["out"] = str(out)
    return done


def read_record(path: Path) -> dict:
    """A ``finetune`` record: ``path`` (``curve.json``) or ``path/curve.json``; one-line errors for anything else."""
    from omnirecon.data.io import read_json

    file = Path(path) / "curve.json" if Path(path).is_dir() else Path(path)
    fix = "pass the --out folder of `omnirecon finetune` (it holds curve.json)"
    if not file.is_file():
        raise InputError("no finetune record (curve.json) here", path, fix)
    try:
        record = read_json(file)
    except Exception as e:  # noqa: BLE001 - any unreadable file is the same one-line error
        raise InputError(f"cannot read the finetune record ({type(e).__name__})", file, fix) from None
    if not isinstance(record, dict) or not isinstance(record.get("sources", []), list):
        raise InputError("not a finetune record (no list of sources)", file, fix)
    return record


def bundle_views(cfg: ExportConfig, scene, record: dict | None) -> list[int]:
    """The views the bundle holds: ``--views``; else the finetune record's sources (every view it blended); else
    ``--num-views`` evenly spaced train views; else every train view (as the real-time mesh path blends)."""
    if cfg.views:
        return check_views(cfg.views, len(scene), cfg.scene)
    if record is not None and record.get("sources"):
        return check_views([str(v) for v in record["sources"]], len(scene), cfg.finetune)
    if cfg.num_views:
        return default_views(scene, cfg.num_views)
    return list(scene.splits.get("train") or range(len(scene)))
