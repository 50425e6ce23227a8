"""``omnirecon mesh``: a mesh from depth maps (stereo and/or a model's rendered depth), in the input frame.

The pipeline is :mod:`omnirecon.mesh.build`'s (``--fusion reference``: VolRecon / Omni-Recon's protocol,
the Omni-Recon spec §6, as a preset). Outputs, for ``--out mesh.ply`` (any of ``.ply .obj .glb``, several allowed)::

    mesh.ply            the cleaned mesh in the input scene's frame (``Scene.to_input`` applied)
    mesh_metrics.json   settings, face counts, seconds per stage and the geometry metrics the scene
                        allows (silhouette IoU on held-out masks, depth errors, Chamfer / F-score
                        against a procedural scene's exact mesh), lengths in input units
    mesh_preview.png    the mesh drawn from the first source view (flat shading)
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Literal

import tyro

from omnirecon.data import detect_format
from omnirecon.data.io import write_json
from omnirecon.engine.machine import MachineConfig, ModelChoice, load_model, pick_device, set_threads
from omnirecon.engine.protocols import protocol_for
from omnirecon.engine.scenes import load_at_resolution, photo_side
from omnirecon.engine.views import check_views, default_views, held_out_views
from omnirecon.errors import InputError
from omnirecon.mesh import geometry
from omnirecon.mesh.build import PRESETS, MeshOptions, default_depth, default_surface, mesh_from_model
from omnirecon.mesh.confidence import NoDepth
from omnirecon.mesh.files import check_mesh_paths, read_mesh, to_input_frame, write_mesh
from omnirecon.options import Meshing, Overwrites, PhotoSize, SceneInput, SourceViews, check_options
from omnirecon.outputs import remove_written
from omnirecon.progress import progress_bar

PREVIEW_SIDE = 512
"""Long side of the preview picture in pixels (the source camera, upscaled, never downscaled)."""
@dataclass
class MeshConfig(Overwrites, SourceViews, ModelChoice, SceneInput, PhotoSize, Meshing, MachineConfig):
    """Extract a mesh: depth at the views (classical stereo, a checkpoint's or the plane-sweep floor's
    rendered depth, or both), fused into a TSDF over the scene bounds, marching cubes, cleaning (with
    the masks for objects), a face budget and completion (every content pixel of every view gets a
    surface); written in the input scene's frame with its metrics."""

    views: tuple[str, ...] | None = None
    """View indices to render depth at (default: 23 24 33 on DTU, else --num-views evenly spaced train
    views), or `all`: every training view, each rendered from its own --num-views nearest views."""
    out: tuple[Path, ...] = ()
    """Mesh file(s): .ply, .obj and/or .glb (default: outputs/mesh/<scene>_<model>.ply)."""
    depth: Literal["auto", "model", "stereo", "stereo+model", "oracle"] = "auto"
    """Depth source: the model's rendered depth, classical stereo (OpenCV SGBM on neighbour pairs; needs
    no model), stereo with the model's depth where stereo finds none, or a procedural scene's exact
    depth; `auto`: the measured best for the scene kind: stereo on forward-facing captures and with --masks,
    stereo+model on other object rigs, stereo without a model (omnirecon.mesh.build.default_depth)."""
    shifts: tuple[float, ...] | None = None
    """Virtual views per view: shifts along the camera x axis as fractions of its distance to the
    scene centre (default: the preset's: 0 for fit, VolRecon's 25 mm on DTU for reference)."""
    trunc: float | None = None
    """TSDF truncation in voxels (default: the preset's: 4 for `fit`, widened to twice the depth error the
    maps show; 3 for `reference`, VolRecon's)."""
    fusion: Literal["fit", "reference"] = "fit"
    """`fit`: confidence-weighted fusion scaled to the depth (omnirecon.mesh.fusion); `reference`:
    VolRecon's protocol as published."""
    weights: bool | None = None
    """Weight each pixel by how many other depth maps agree with it (forward-backward reprojection;
    default: the preset's, on for fit)."""
    max_faces: int = 400_000
    """Face budget of the written mesh (0 = keep every face): completion's fills and a forward-facing scene's
    backdrop sheet count, the fused surface gets what they leave. A smaller budget costs the real captures
    held-out PSNR for little mesh-path speed (face counts, scores and frame times per budget: BENCHMARKS "Depth
    sources", "Real-time mesh path")."""
    depth_pass: Literal["auto", "coarse", "fine"] = "auto"
    """Pass of IBRNet / Omni-Recon that renders the depth maps: fine (better geometry) or coarse (about 5x
    faster); `auto`: coarse for stereo+model (the model only fills stereo's holes; what bench/depth_sources.py
    measured), fine otherwise."""
    min_acc: float = 0.5
    """Models that return accumulated opacity (IBRNet): pixels below it get no depth."""
    min_views: int = 2
    """Keep vertices inside the masks of at least this many source views."""
    min_component: float = 0.001
    """Drop connected components smaller than this fraction of the largest (by faces)."""
    cull_hidden: bool = True
    """Drop faces no source pixel ray (inside the masks) hits first."""
    metrics: bool = True
    """Score the mesh and write <out>_metrics.json."""
    preview: bool = True
    """Write <out>_preview.png (the mesh seen from the first source view)."""
    surface: Literal["auto", "fusion", "poisson", "coherent"] = "auto"
    """`auto`: per scene kind (omnirecon.mesh.build.default_surface: `coherent` on a walk, `fusion` elsewhere);
    `fusion`: the fused TSDF surface (with --complete: fills from each view's own depth cover every content pixel);
    `coherent`: one screened-Poisson surface from the depth several views confirm, kept only where views support it,
    no fills (omnirecon.mesh.surface); `poisson` (with --masks): screened Poisson over the fused surface, trimmed to
    the masks. `coherent` and `poisson` need the `surface` extra (pymeshlab)."""
    complete: tyro.conf.DisallowNone[bool | None] = None
    """Give every content pixel of every view a surface (fill from the view's own depth, a backdrop on
    forward-facing scenes, hole filling); default (None): the preset's, on for `fit`; `reference` never completes."""

    def mesh_options(self, scene=None, has_model: bool = True) -> MeshOptions:
        """The pipeline's settings: the --fusion preset, with every option of this command that names a
        :class:`MeshOptions` field on top when given (``None`` and ``auto`` are not given, and a flag left at its
        default yields to a preset that sets it: ``--fusion reference`` keeps its face budget, its completion and its
        sources per depth map, every view, unless --num-views is given). InputError for flags that cannot work
        together (:meth:`check_together`)."""
        self.check_together()
        preset = PRESETS.get(self.fusion, {})
        given = {}
        for f in fields(MeshConfig):
            name = "neighbours" if f.name == "num_views" else f.name  # --num-views: sources per depth map
            value = getattr(self, f.name)
            if name not in MESH_FIELDS or value is None or value == "auto" or (value == f.default and name in preset):
                continue
            given[name] = tuple(value) if isinstance(value, list) else value
        depth = self.depth if self.depth != "auto" else default_depth(scene, has_model, self.masks)
        surface = self.surface if self.surface != "auto" else default_surface(scene, self.masks)
        depth_pass = self.depth_pass if self.depth_pass != "auto" else "coarse" if depth == "stereo+model" else "fine"
        return MeshOptions.preset(self.fusion, **{**given, "depth": depth, "surface": surface, "depth_pass": depth_pass,
                                                  "chunk": self.chunk})

    def check_together(self) -> None:
        """InputError (one line, the fix named) for flags that cannot work together."""
        if self.surface == "poisson" and not self.masks:
            raise InputError("--surface poisson needs --masks: its surface is trimmed to the object masks", None,
                             "add --masks (a scene with object masks), or use --surface fusion or coherent")
        if self.fusion == "reference" and self.complete:
            raise InputError("--complete works only with --fusion fit (reference, VolRecon's protocol, never completes)",
                             None, "drop --complete, or use --fusion fit")


MESH_FIELDS = frozenset(f.name for f in fields(MeshOptions)) - {"fusion"}
"""The :class:`MeshOptions` fields a command option of the same name sets (``--fusion`` picks the preset)."""


def run_mesh(cfg: MeshConfig) -> dict:
    """Run ``omnirecon mesh``; returns the record written to ``<out>_metrics.json`` (plus ``files``)."""
    cfg.mesh_options().check()  # bad options fail before any work
    check_options("mesh", cfg)  # the numbers (omnirecon/options.py); here for callers other than the CLI
    outs = check_mesh_paths(cfg.out) if cfg.out else None
    set_threads(cfg.threads)
    device = pick_device(cfg.device)
    net, info, scene, fmt, load_seconds = load_inputs(cfg, device)
    views = check_views(cfg.views, len(scene), cfg.scene, scene) if cfg.views else default_views(scene, cfg.num_views)
    if cfg.surface == "poisson" and scene.masks is None:
        raise InputError("--surface poisson needs object masks, and the scene has none", cfg.scene,
                         "use --surface fusion or coherent, or a scene with masks")
    options = cfg.mesh_options(scene, net is not None)
    options.check()
    if outs is None:
        outs = [Path("outputs/mesh") / f"{Path(cfg.scene).name}_{info['name']}.ply"]
    with progress_bar(transient=False) as bar:
        try:
            made = mesh_from_model(net, scene, views, options, device, cfg.masks, bar)
        except NoDepth as e:
            e.path = Path(cfg.scene)  # the line names the scene whose views gave no depth
            raise
    if len(made.mesh.faces) == 0:
        raise InputError("the mesh is empty: no fused surface survived (see the depth maps and masks)", cfg.scene,
                         "try a trained checkpoint, more --views, --no-masks or a larger --voxel")
    record = made.info
    record["seconds"]["load"] = load_seconds
    record["seconds"]["images_to_mesh"] = sum(v for k, v in record["seconds"].items() if k != "images_to_mesh")
    record.update({"scene": str(cfg.scene), "format": fmt, "resolution": [scene.width, scene.height],
                   "model": info, "device": device, "frame": "input", "to_input": scene.to_input.tolist()})
    return write_set(cfg, made, scene, views, outs, record)


def load_inputs(cfg: MeshConfig, device: str):
    """``(model or None, model info, scene, its format, seconds to load the scene)``; a damaged ground-truth mesh is named
    here, before any mesh is written."""
    fmt = detect_format(cfg.scene)
    if cfg.ckpt is None and cfg.model is None and cfg.depth in ("stereo", "oracle"):
        net, info = None, {"name": cfg.depth, "preset": None, "checkpoint": None}
    else:
        net, info = load_model(cfg.ckpt, cfg.model, device)
    proto = protocol_for(Path(cfg.scene), fmt)
    start = time.perf_counter()
    scene = load_at_resolution(cfg.scene, cfg.resolution or photo_side(Path(cfg.scene), fmt=fmt), proto.background, fmt)
    load_seconds = time.perf_counter() - start
    if cfg.metrics and scene.mesh_path is not None:
        geometry.load_mesh_file(scene.mesh_path, "ground-truth mesh", "fix the scene's mesh file, or remove its "
                                "mesh_path entry (or pass --no-metrics)")
    return net, info, scene, fmt, load_seconds


def write_set(cfg: MeshConfig, made, scene, views: list[int], outs: list[Path], record: dict) -> dict:
    """Score the mesh and write the set (meshes in the input frame, preview, metrics), renamed into place
    together, so an interrupt leaves the previous set or the new one; members of the previous set this run
    does not write go. Returns ``record`` with ``files`` and the meshes in memory (``meshes``)."""
    mesh = made.mesh
    stem = outs[0].with_suffix("")
    extra = {}
    if cfg.preview:
        cam = scene.cameras[views[0]]
        cam = cam.rescaled(max(1.0, PREVIEW_SIDE / max(cam.width, cam.height)))
        extra[Path(f"{stem}_preview.png")] = lambda tmp: geometry.save_picture(tmp, mesh, cam)
    if cfg.metrics:
        start = time.perf_counter()
        record["metrics"] = geometry.score_mesh(made, scene, held_out_views(scene, views))
        record["seconds"]["metrics"] = time.perf_counter() - start
        extra[Path(f"{stem}_metrics.json")] = lambda tmp: write_json(tmp, record)
    previous = previous_set(stem)
    record["files"] = [str(p) for p in [*outs, *extra]]
    in_input = to_input_frame(mesh, scene.to_input)
    files = write_mesh(in_input, outs, extra=extra)
    for p in previous - {Path(f) for f in record["files"]}:
        remove_written(p)  # only a file this tool wrote (and the user did not replace since)
    record["files"] = [str(p) for p in [*files, *extra]]
    record["meshes"] = {"scene": mesh, "input": in_input}  # in memory, for reconstruct's next stages (not JSON)
    return record


def set_files(cfg: MeshConfig) -> list[Path]:
    """Every file ``cfg`` writes for its ``--out`` list: the meshes and the side files of the first one."""
    stem = Path(cfg.out[0]).with_suffix("")
    return [*map(Path, cfg.out), *([Path(f"{stem}_preview.png")] if cfg.preview else []),
            *([Path(f"{stem}_metrics.json")] if cfg.metrics else [])]


def previous_set(stem: Path) -> set[Path]:
    """The files an earlier ``omnirecon mesh`` run wrote for ``stem`` (listed in its ``<stem>_metrics.json``;
    only names of that set, beside it)."""
    import json

    try:
        listed = json.loads(Path(f"{stem}_metrics.json").read_text()).get("files", [])
    except (OSError, ValueError, AttributeError):
        return set()
    names = {f"{stem.name}{s}" for s in (".ply", ".obj", ".glb", "_preview.png", "_metrics.json")}
    return {Path(f) for f in listed if isinstance(f, str) and Path(f).parent == stem.parent and Path(f).name in names}


def summary_lines(record: dict) -> list[str]:
    """Human-readable lines about a :func:`run_mesh` record."""
    s = record["seconds"]
    faces = record["faces"].get("final", record["faces"].get("decimated", record["faces"].get("components", 0)))
    lines = [f"{record['vertices']:,} vertices, {faces:,} faces from "
             f"{record['depth_maps']} depth maps ({record['valid_depth_fraction']:.0%} of pixels with depth), "
             f"views {record['views']}" + (f", grid {'x'.join(map(str, record['grid']))}" if record.get("grid") else
                                          f", coherent surface from {record['surface'].get('points', 0):,} confirmed "
                                          f"points"),
             f"images to mesh {s['images_to_mesh']:.1f} s (" + ", ".join(
                 f"{k.replace('_', ' ')} {v:.1f}" for k, v in s.items() if k not in ("images_to_mesh", "metrics")) + ")"]
    comp = record.get("completion")
    if comp and "coverage_before" in comp:
        lines.append(f"completion: {comp['fill_faces']:,} fill faces; the views' content pixels covered "
                     f"{comp['coverage_before']:.1%} by the fused mesh, 100% after")
    elif comp and comp.get("backdrop_faces"):
        lines.append(f"background layer: {comp['backdrop_faces']:,} faces on the bounds' far side (no fills)")
    m = record.get("metrics", {})
    if "mask_iou" in m:
        against = {"masks": "the object masks", "exact depth": "every surface they see"}.get(m["mask_iou"].get("against"),
                                                                                             "the masks")
        lines.append(f"silhouette IoU on {len(m['held_out'])} held-out views (against {against}): "
                     f"{m['mask_iou']['mean']:.3f}")
    for key, what in (("rendered_depth", "model depth maps vs GT mesh"), ("depth", "mesh depth at held-out views")):
        if key in m:
            d = m[key]
            lines.append(f"{what}: abs rel {d['abs_rel']:.3f}, RMSE {d['rmse']:.4g}, delta<1.25 {d['delta1']:.3f}, "
                         f"coverage {d['coverage']:.2f}")
    if "chamfer" in m:
        c = m["chamfer"]
        lines.append(f"Chamfer {c['chamfer']:.4g} (accuracy {c['accuracy']:.4g}, "
                     f"completeness {c['completeness']:.4g}), "
                     f"F-score {c['fscore']:.3f} at {c['threshold']:.3g} (input units; diagonal {m['diagonal']:.3g})")
    return lines


def scene_frame_mesh(path: Path, mesh_file: Path, long_side: int):
    """The scene at ``long_side`` (normalised, as models see it) and ``mesh_file`` (input frame, as
    ``omnirecon mesh`` writes it) moved into that frame. Returns ``(scene, trimesh.Trimesh)``."""
    scene = load_at_resolution(path, long_side)
    return scene, read_mesh(mesh_file, scene.to_input)
