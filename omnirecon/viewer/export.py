"""Export (``omnirecon export``): a mesh with baked vertex colours (PLY, GLB) and a static web-viewer bundle.

Outputs in ``--out DIR``::

    mesh.ply, mesh.glb   the mesh in the input frame (``Scene.to_input``) with per-vertex RGBA colours
                         baked by :mod:`omnirecon.mesh.bake` (uint8, the image values as they are:
                         not converted to linear, so both files carry the same numbers)
    viewer/              the viewer bundle (:mod:`omnirecon.viewer.bundle`); ``omnirecon view DIR``
    export.json          what was done: scene, views, model, mesh source, counts, bake statistics, seconds

The mesh comes from ``--mesh FILE`` (input frame, e.g. the output of ``omnirecon mesh``) or from
:func:`omnirecon.mesh.build.mesh_from_model` at the source views. Every file is written atomically;
the bundle folder is built beside its final place and swapped in.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from omnirecon.data.io import write_json
from omnirecon.errors import InputError
from omnirecon.mesh.bake import BakeOptions, bake_vertex_colors, colored_mesh
from omnirecon.mesh.build import mesh_from_model
from omnirecon.mesh.files import to_scene_frame, write_mesh
from omnirecon.mesh.ibr import MeshRenderer, realtime_options
from omnirecon.options import check_value
from omnirecon.rays import Sources
from omnirecon.viewer.bundle import three_unavailable_reason, write_bundle


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
    blend: str | None = None
    """The blend the viewer starts with (``MeshRenderOptions.blend``: ``network`` or ``angle``; it can switch); None:
    the scene's real-time default (:func:`omnirecon.mesh.ibr.realtime_setting`, as every option below)."""
    angle_sources: int | None = None
    """Sources per point of the angle blend (``MeshRenderOptions.angle_sources``; 0: all); the real-time default is
    ``omnirecon.mesh.ibr.REALTIME_ANGLE_SOURCES``, what finetune chose on the DTU scans."""
    frame_sources: int | None = None
    """Sources per frame of the network blend, the nearest to the frame's camera among the bundled views (0: all;
    ``finetune --nearest``, ``omnirecon.mesh.ibr.REALTIME_SOURCES``)."""
    fill: str | None = None
    """Where no triangle covers a pixel (``MeshRenderOptions.fill``: ``far``, ``nearest`` or ``background``)."""
    cracks: int | None = None
    """The crack fill's radius (``MeshRenderOptions.cracks``; 0: off)."""
    source_masks: bool | None = None
    """The angle blend weighs each source by its object mask (``MeshRenderOptions.source_masks``; scenes whose masks
    hold everything photographed only: :func:`omnirecon.mesh.ibr.masks_hold_scene`)."""
    max_edge: float = 0.0
    """Subdivide triangles until no edge is longer than this fraction of the scene bounds' diagonal
    before baking (0: keep the mesh as it is). Vertex colours can only be as fine as the vertices: a
    coarse mesh (a ground plane of two triangles) needs this to carry its texture."""

    def check(self) -> None:
        for name in ("bake_views", "visibility_tol", "max_edge", "angle_sources", "cracks"):
            check_value(name, getattr(self, name))  # the rules: omnirecon/options.py
        if self.blend not in (None, "network", "angle"):
            raise InputError(f"--blend must be network or angle, got {self.blend!r}", None, "use e.g. --blend angle")
        if self.fill not in (None, "far", "nearest", "background"):
            raise InputError(f"--fill must be far, nearest or background, got {self.fill!r}", None,
                             "use e.g. --fill nearest")
        if (self.frame_sources or 0) < 0:
            raise InputError(f"frame_sources must be >= 0, got {self.frame_sources}", None, "use e.g. 6 (0: all)")

    def setting(self, scene, record: dict | None = None) -> dict:
        """The real-time setting the bundle starts with: :func:`omnirecon.mesh.ibr.realtime_setting` of ``scene`` and
        ``record`` (a ``finetune`` record: what it scored), then the options given here."""
        from omnirecon.mesh.ibr import masks_hold_scene, realtime_setting

        out = realtime_setting(scene, record)
        given = {"blend": self.blend, "angle_sources": self.angle_sources, "sources": self.frame_sources,
                 "fill": self.fill, "cracks": self.cracks, "source_masks": self.source_masks}
        out.update({k: v for k, v in given.items() if v is not None})
        out["source_masks"] = bool(out["source_masks"]) and masks_hold_scene(scene)
        return out


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


def selection(scene) -> dict:
    """How the viewer's network blend picks each frame's sources, as :func:`omnirecon.engine.views.select_sources`:
    ``{"metric": "angle", "center": [3]}`` (the angle around the point nearest every optical axis of the scene) on
    object rigs, ``{"metric": "distance", "center": None}`` otherwise (model frame)."""
    from omnirecon.cameras import closest_point_to_axes
    from omnirecon.engine.views import view_metric

    if view_metric(scene) != "angle":
        return {"metric": "distance", "center": None}
    return {"metric": "angle", "center": closest_point_to_axes(scene.cameras).double().tolist()}


def export_scene(model, scene, views, out: Path, mesh: trimesh.Trimesh | None = None, mesh_options=None,
                 options: ExportOptions | None = None, device: str = "cpu", info: dict | None = None,
                 use_masks: bool = True, progress=None, finetune: dict | None = None, mesh_views=None) -> dict:
    """Bake and export ``scene``'s mesh as seen by ``model`` with sources ``views``.

    Args:
        model: An Omni-Recon model (the bundle needs its appearance branch; the bake only ``encode`` and
            ``shade``).
        scene: The normalised :class:`~omnirecon.data.scene.Scene` (its ``to_input`` maps to the input frame).
        views: Source view indices: every view the viewer may blend (the real-time path: every training view).
        finetune: A ``finetune`` record (``curve.json``): the viewer starts with what it scored
            (:meth:`ExportOptions.setting`).
        mesh_views: Without ``mesh``: the views to mesh from (default: ``views``).
        out: Output folder.
        mesh: The mesh in the **input** frame, or ``None`` to mesh the scene with the model
            (:func:`~omnirecon.mesh.build.mesh_from_model`, ``mesh_options``).
        info: The model's description for the records (``omnirecon.engine.evaluate.load_model``'s ``info``).
        use_masks: Without ``mesh``: clean the mesh with the source views' object masks.

    Returns:
        The record written to ``export.json`` (plus ``files``).
    """

    options = options or ExportOptions()
    options.check()
    if options.viewer and three_unavailable_reason():
        raise InputError(three_unavailable_reason(), None, "or pass --no-viewer to write only mesh.ply and mesh.glb")
    if not model.capabilities.appearance:
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
        made = mesh_from_model(model, scene, views if mesh_views is None else [int(v) for v in mesh_views], mesh_options,
                               device, use_masks, progress)
        mesh_model, record["mesh"] = made.mesh, {"source": "mesh_from_model", **made.info}
    else:
        mesh_model = to_scene_frame(mesh, scene.to_input)
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
    setting = options.setting(scene, finetune)
    start = time.perf_counter()
    render_opts = realtime_options(setting, background=background, visibility=True,
                                   visibility_tol=options.visibility_tol)
    with MeshRenderer(model, (verts, faces), sources, render_opts) as renderer:
        seconds["encode"] = time.perf_counter() - start
        start = time.perf_counter()
        bake = bake_vertex_colors(renderer, verts, faces, BakeOptions(views=options.bake_views), background)
        seconds["bake"] = time.perf_counter() - start
        colored = colored_mesh(verts, faces, bake.colors, scene.to_input)
        files = write_mesh(colored, [out / "mesh.ply", out / "mesh.glb"])
        record.update({"vertices": len(verts), "faces": len(faces), "bake": {**bake.summary(),
                       "views": options.bake_views, "visibility_tol": options.visibility_tol},
                       "background": list(background), "rasterizer": renderer.rasterizer.backend})
        if options.viewer:
            start = time.perf_counter()
            names = [scene.names[i] for i in views] if scene.names else None
            extra = {"model": info or {}, "bake": record["bake"], "scene": record["scene"], "views": views}
            files.append(write_bundle(out / "viewer", renderer, (out / "mesh.glb").read_bytes(), verts, faces,
                                      scene.to_input, background, names, options.visibility, extra, setting, views,
                                      selection(scene)))
            seconds["viewer"] = time.perf_counter() - start
    record["setting"] = setting
    record["seconds"] = seconds
    write_json(out / "export.json", record)
    files.append(out / "export.json")
    record["files"] = [str(p) for p in files]
    return record
