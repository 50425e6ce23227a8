"""``omnirecon export``: a mesh with baked vertex colours (PLY, GLB) and a static web-viewer bundle.

Outputs in ``--out DIR``::

    mesh.ply, mesh.glb   the mesh in the input frame (``Scene.to_input``) with per-vertex RGBA colours
                         baked by :mod:`omnirecon.render.bake` (uint8, the image values as they are:
                         not converted to linear, so both files carry the same numbers)
    viewer/              the viewer bundle (:mod:`omnirecon.viewer.bundle`); ``omnirecon view DIR``
    export.json          what was done: scene, views, model, mesh source, counts, bake statistics, seconds

The mesh comes from ``--mesh FILE`` (input frame, e.g. the output of ``omnirecon mesh``) or from
:func:`omnirecon.render.mesh.mesh_from_model` at the source views. Every file is written atomically;
the bundle folder is built beside its final place and swapped in.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import trimesh

from omnirecon.errors import InputError
from omnirecon.outputs import prepare_out
from omnirecon.preflight import check_resolution


@dataclass
class ExportOptions:
    """Settings of :func:`export_scene`."""

    bake_views: int = 3
    """Most frontal visible source views blended per vertex for the baked colours."""
    visibility: bool = True
    """The viewer starts with the per-source occlusion test on (the bake always uses it)."""
    visibility_tol: float = 0.01
    """Relative depth tolerance of the occlusion test."""
    viewer: bool = True
    """Write the viewer bundle (needs three.js from npm)."""
    max_edge: float = 0.0
    """Subdivide triangles until no edge is longer than this fraction of the scene bounds' diagonal
    before baking (0: keep the mesh as it is). Vertex colours can only be as fine as the vertices: a
    coarse mesh (a ground plane of two triangles) needs this to carry its texture."""

    def check(self) -> None:
        if self.bake_views < 1:
            raise InputError(f"--bake-views must be at least 1, got {self.bake_views}", None, "use e.g. 3")
        if not 0 <= self.visibility_tol < 1:
            raise InputError(f"--visibility-tol must be in [0, 1), got {self.visibility_tol}", None, "use e.g. 0.01")
        if not (self.max_edge == 0 or 1e-4 <= self.max_edge <= 1):
            raise InputError(f"--max-edge must be 0 (off) or in [1e-4, 1], got {self.max_edge}", None, "use e.g. 0.005")


def read_mesh(path: Path) -> trimesh.Trimesh:
    """A triangle mesh file (PLY, OBJ, GLB, ...) as one ``trimesh.Trimesh``; one-line errors."""
    path = Path(path)
    if not path.is_file():
        raise InputError("mesh file is missing", path, "pass a mesh written by `omnirecon mesh` (.ply, .obj, .glb)")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # noqa: BLE001 - trimesh raises many types for bad files
        raise InputError(f"cannot read mesh ({type(e).__name__}: {e})", path, "pass a valid .ply, .obj or .glb") from e
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError("the file holds no triangles", path, "pass a triangle mesh")
    if not np.isfinite(np.asarray(mesh.vertices)).all():
        raise InputError("the mesh has non-finite vertices", path, "pass a valid mesh")
    return mesh


def subdivide(vertices: np.ndarray, faces: np.ndarray, max_edge: float, max_faces: int = 4_000_000):
    """Split triangles until no edge exceeds ``max_edge`` (midpoint subdivision, geometry unchanged; the
    original vertices keep their indices)."""
    from trimesh.remesh import subdivide_to_size

    edges = np.linalg.norm(vertices[faces] - vertices[faces[:, [1, 2, 0]]], axis=-1)  # [F, 3]
    # each halving of the longest edges multiplies those faces by 4
    estimate = float((4.0 ** np.ceil(np.log2(np.maximum(edges.max(1) / max_edge, 1.0)))).sum())
    if estimate > max_faces:
        raise InputError(f"--max-edge would make about {estimate:,.0f} faces (limit {max_faces:,})", None,
                         "use a larger --max-edge")
    v, f = subdivide_to_size(vertices, faces, max_edge, max_iter=32)
    return np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)


def export_scene(model, scene, views, out: Path, mesh: trimesh.Trimesh | None = None, mesh_options=None,
                 options: ExportOptions | None = None, device: str = "cpu", info: dict | None = None,
                 use_masks: bool = True, progress=None) -> dict:
    """Bake and export ``scene``'s mesh as seen by ``model`` with sources ``views``.

    Args:
        model: An Omni-Recon model (the bundle needs its appearance branch; the bake only ``encode`` and
            ``shade``).
        scene: The normalised :class:`~omnirecon.data.scene.Scene` (its ``to_input`` maps to the input frame).
        views: Source view indices.
        out: Output folder.
        mesh: The mesh in the **input** frame, or ``None`` to mesh the scene with the model
            (:func:`~omnirecon.render.mesh.mesh_from_model`, ``mesh_options``).
        info: The model's description for the records (``omnirecon.eval.load_model``'s ``info``).
        use_masks: Without ``mesh``: clean the mesh with the source views' object masks.

    Returns:
        The record written to ``export.json`` (plus ``files``).
    """
    from omnirecon.data.io import write_json
    from omnirecon.models.base import Sources
    from omnirecon.render.bake import BakeOptions, bake_vertex_colors, colored_mesh
    from omnirecon.render.mesh import export_mesh, mesh_from_model, to_input_frame
    from omnirecon.render.mesh_ibr import MeshRenderer, MeshRenderOptions
    from omnirecon.viewer.bundle import three_unavailable_reason, write_bundle

    options = options or ExportOptions()
    options.check()
    if options.viewer and three_unavailable_reason():
        raise InputError(three_unavailable_reason(), None, "or pass --no-viewer to write only mesh.ply and mesh.glb")
    if not all(hasattr(model, a) for a in ("encode", "shade")):
        raise InputError(f"{type(model).__name__} cannot shade surface points (no appearance branch)", None,
                         "export a checkpoint of an omnirecon-* preset")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output path is a file", out, "pass a folder for --out")
    views = [int(v) for v in views]
    seconds = {}
    record = {"scene": str(scene.path) if scene.path else None, "views": views, "model": info or {},
              "frame": "input", "to_input": scene.to_input.tolist()}
    start = time.perf_counter()
    if mesh is None:
        made = mesh_from_model(model, scene, views, mesh_options, device, use_masks, progress)
        mesh_model, record["mesh"] = made.mesh, {"source": "mesh_from_model", **made.info}
    else:
        mesh_model = to_input_frame(mesh, torch.linalg.inv(scene.to_input.double()))
        record["mesh"] = {"source": "file"}
    seconds["mesh"] = time.perf_counter() - start
    if len(mesh_model.faces) == 0:
        raise InputError("the mesh is empty", scene.path, "try a trained checkpoint, more --views or --mesh FILE")
    verts = np.asarray(mesh_model.vertices, dtype=np.float64)
    faces = np.asarray(mesh_model.faces, dtype=np.int64)
    if options.max_edge > 0:
        start = time.perf_counter()
        edge = options.max_edge * float((scene.bounds[1] - scene.bounds[0]).double().norm())
        verts, faces = subdivide(verts, faces, edge)
        record["mesh"]["subdivided"] = {"max_edge": edge, "faces_before": len(mesh_model.faces)}
        seconds["subdivide"] = time.perf_counter() - start
    background = tuple(float(c) for c in (scene.background or (1.0, 1.0, 1.0)))
    model = model.to(device).eval()
    sources = Sources.from_scene(scene, views).to(device)
    start = time.perf_counter()
    render_opts = MeshRenderOptions(background=background, visibility=True, visibility_tol=options.visibility_tol)
    with MeshRenderer(model, (verts, faces), sources, render_opts) as renderer:
        seconds["encode"] = time.perf_counter() - start
        start = time.perf_counter()
        bake = bake_vertex_colors(renderer, verts, faces, BakeOptions(views=options.bake_views), background)
        seconds["bake"] = time.perf_counter() - start
        colored = colored_mesh(verts, faces, bake.colors, scene.to_input)
        files = export_mesh(colored, [out / "mesh.ply", out / "mesh.glb"])
        record.update({"vertices": len(verts), "faces": len(faces), "bake": {**bake.summary(),
                       "views": options.bake_views, "visibility_tol": options.visibility_tol},
                       "background": list(background), "rasterizer": renderer.rasterizer.backend})
        if options.viewer:
            start = time.perf_counter()
            names = [scene.names[i] for i in views] if scene.names else None
            extra = {"model": info or {}, "bake": record["bake"], "scene": record["scene"], "views": views}
            files.append(write_bundle(out / "viewer", renderer, (out / "mesh.glb").read_bytes(), verts, faces,
                                      scene.to_input, background, names, options.visibility, extra))
            seconds["viewer"] = time.perf_counter() - start
    record["seconds"] = seconds
    write_json(out / "export.json", record)
    files.append(out / "export.json")
    record["files"] = [str(p) for p in files]
    return record


@dataclass
class ExportConfig:
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
    device: str = "auto"
    """cpu, cuda or auto."""
    threads: int | None = None
    """torch CPU threads (default: torch's choice; use 1 when other jobs share the cores)."""
    background: Literal["white", "black"] = "white"
    """Colour RGBA inputs are composited on."""

    def main(self) -> None:
        prepare_out(self.out)  # writable, stale temporaries gone: before any work
        record = run_export(self)
        for p in record["files"]:
            print(f"wrote {p}")
        b = record["bake"]
        print(f"{record['vertices']:,} vertices, {record['faces']:,} faces; baked from {b['mean_views']:.2f} views per "
              f"vertex on average ({b['fallback']} fallback, {b['unseen']} unseen)")
        if self.viewer:
            print(f"view it: omnirecon view {record['out']}")


def run_export(cfg: ExportConfig) -> dict:
    """Run ``omnirecon export``; returns :func:`export_scene`'s record (plus ``out``)."""
    from omnirecon.data import detect_format
    from omnirecon.eval import load_at_resolution, load_model, pick_device, protocol_for, set_threads
    from omnirecon.mesh_cli import check_views, default_views
    from omnirecon.render.mesh import MeshOptions

    options = ExportOptions(cfg.bake_views, cfg.visibility, cfg.visibility_tol, cfg.viewer, cfg.max_edge)
    options.check()
    check_resolution(cfg.resolution)
    if cfg.num_views < 1:
        raise InputError(f"--num-views must be at least 1, got {cfg.num_views}", None, "use e.g. 3")
    mesh = read_mesh(cfg.mesh) if cfg.mesh is not None else None
    set_threads(cfg.threads)
    device = pick_device(cfg.device)
    fmt = detect_format(cfg.scene)
    net, info = load_model(cfg.ckpt, None, device)
    proto = protocol_for(Path(cfg.scene), fmt)
    scene = load_at_resolution(cfg.scene, cfg.resolution or proto.long_side, cfg.background, fmt)
    views = check_views(cfg.views, len(scene), cfg.scene) if cfg.views else default_views(scene, cfg.num_views)
    out = cfg.out or Path("outputs/export") / Path(cfg.scene).name
    mesh_options = MeshOptions(voxel=cfg.voxel)
    if mesh is None:
        mesh_options.check()
    if mesh is None:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                      TimeElapsedColumn()) as bar:
            record = export_scene(net, scene, views, out, None, mesh_options, options, device, info, cfg.masks, bar)
    else:
        record = export_scene(net, scene, views, out, mesh, mesh_options, options, device, info, cfg.masks)
    record["out"] = str(out)
    return record
