"""Real-time image-based mesh rendering with Omni-Recon's appearance branch (``shared/docs/omnirecon.md`` §7).

Per frame: rasterize the mesh at the target camera (:mod:`omnirecon.render.raster`) -> one surface
point per covered pixel -> the appearance branch blends the source views there
(``omega = softmax_i MLP([ReLU(Linear(F_i(x))); u - u_i])``, colour ``sum_i omega_i c_i``) ->
background colour elsewhere. The geometry branch and the feature volume are neither used nor computed, and the
source features are encoded once per scene by :class:`MeshRenderer`, not per frame.

**The blend** is :mod:`omnirecon.mesh.kernel`'s (visible sources, occlusion test, network or angle weights,
source masks, consensus, colour), computed per point by :class:`omnirecon.mesh.shader.SourceShader`, the base class
of :class:`MeshRenderer`; ``finetune`` scores and tunes with the same functions (:mod:`omnirecon.mesh.pixels`). This
module is its real-time wrapper: rasterization, fill, chunks and threads, sets of sources, level of detail.

**Fill** (``MeshRenderOptions.fill``, not in the paper): pixels no triangle covers get the background
layer of :mod:`omnirecon.mesh.fill`, shaded by the same blend; ``render``'s ``mask`` is the coverage. With
``fill="nearest"``, those within reach of a covered pixel first take its rendered z-depth
(:func:`omnirecon.mesh.fill.nearest_depth`), as ``finetune --fill nearest`` scores them. Whatever the fill, the missed
pixels the mesh encloses (``MeshRenderOptions.cracks``, :func:`omnirecon.mesh.fill.crack_pixels`) take it too.

**Sets of sources** (:class:`~omnirecon.mesh.frames.ViewCache`): frames that each blend their own nearest sources (videos, as ``finetune
--nearest`` scores) share one rasterizer, each view's occlusion depths and mask falloff, and one encoding per set
of views; the encoding cannot be shared per view, as the encoder normalises with the batch statistics of the views
it encodes together. The renderer encodes the appearance maps only (``OmniRecon.encode_appearance``: no volume).

**Chunks and threads.** ``MeshRenderOptions.fused`` (the default) shades with the fused shader
(:mod:`omnirecon.mesh.shader`); ``fused=False`` calls ``model.shade`` (any model with ``encode`` and ``shade``).
Points go through in chunks; with ``MeshRenderOptions.workers`` > 1, chunks are shaded by that many threads at once
(each writes its own slice of the outputs): on 2 cores with one torch thread this parallelises every op of a chunk,
where torch's intra-op threads split only the ops above its grain size.

**Frame path** (:meth:`MeshRenderer.frame`, what ``render(extras=False)`` returns): the rasterizer draws
only the z-depth, and each chunk of pixels, in row-major order on the worker threads, unprojects its
pixel centres, puts the fill's layer where the mesh misses, shades and writes its rows of the image, so
nothing but the depth pass runs on one thread. Its reference twin is ``render()`` (rasterized world points,
fill and scatter); ``python -m bench mesh_fps`` times it. With ``MeshRenderOptions.shader`` (by default, where the GL
rasterizer runs) the frame is instead the depth pass, the fill's distance transform on the CPU and one fragment-shader pass in the
rasterizer's GL context (:class:`omnirecon.render.glblend.GLBlend`: the same blend, the viewer's GLSL), whose twin is
this torch shader (``tests/mesh/test_ibr_gl.py``).

**Level of detail and candidate sources** (the real-time videos, ``omnirecon bench --realtime``):
``MeshRenderOptions.face_budget`` (:func:`level_of_detail`, which can also leave out the faces no photo sees:
:func:`photographed_faces`) and ``frame_grid`` (:meth:`MeshRenderer._frame_sources`); all off is the reference path they
are measured against (``python -m bench mesh_lod``).

Size: the renderer's options, its frame and reference paths, the shared per-view cache and the real-time
settings per scene are one real-time path, timed and tested together (the blend is in :mod:`omnirecon.mesh.kernel`
and :mod:`omnirecon.mesh.shader`, the fill's geometry in :mod:`omnirecon.mesh.fill`)."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Literal

import numpy as np
import torch
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.mesh.atlas import TexelAtlas
from omnirecon.mesh.fill import (
    CRACK_RADIUS,
    NEAREST_FILL_REACH,
    exit_depth,
    layer_box,
    nearest_depth,
    ray_basis,
    shaded_surface,
)
from omnirecon.mesh.kernel import block_depth_max, mask_falloff
from omnirecon.mesh.shader import ShadeResult, SourceShader
from omnirecon.rays import Sources
from omnirecon.render.edges import SOFTEN, soften_edges
from omnirecon.render.glblend import GLBlend
from omnirecon.render.raster import Backend, MeshRasterizer, Surface
from omnirecon.scene_kind import SceneKind, scene_kind

if TYPE_CHECKING:
    from omnirecon.mesh.frames import ViewCache


@dataclass
class MeshRenderOptions:
    """Settings of :class:`MeshRenderer`."""

    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Colour of pixels no triangle covers when ``fill="background"`` (DTU: white; procedural scenes:
    ``Scene.background``); also what :meth:`MeshRenderer.render_signal` leaves there."""
    fill: Literal["far", "background", "nearest"] = "far"
    """Where no triangle covers a pixel, :meth:`MeshRenderer.render` shades ``"far"``: the background layer
    of :mod:`omnirecon.mesh.fill` (no pixel left blank), ``"nearest"``: the nearest covered pixel's z-depth within
    :data:`omnirecon.mesh.fill.NEAREST_FILL_REACH` of it and the background layer beyond, or puts ``"background"``:
    that colour."""
    cracks: int = CRACK_RADIUS
    """Whatever ``fill``, the pixels the mesh misses but encloses (:func:`omnirecon.mesh.fill.crack_pixels` of this
    radius: pinholes, seams between completion's fills) take the nearest covered pixel's z-depth (0: off), as
    ``finetune --cracks`` scores them."""
    blend: Literal["network", "angle"] = "network"
    """How a point mixes its sources: ``"network"``, the appearance branch's weights; ``"angle"``,
    :func:`~omnirecon.mesh.kernel.angle_weights` over the ``angle_sources`` sources nearest by viewing angle that see it."""
    angle_sources: int = 4
    """With ``blend="angle"``: sources blended per point (0: every source that sees it); ``finetune --angle-sources``
    (:data:`REALTIME_ANGLE_SOURCES`)."""
    consensus: float = 0.0
    """With ``blend="angle"``: :func:`~omnirecon.mesh.kernel.consensus_weights`' width in RGB (0: off); ``finetune --consensus``."""
    source_masks: bool = False
    """With ``blend="angle"`` and sources that carry object masks (``Sources.masks``): each source's weight times
    :func:`~omnirecon.mesh.kernel.mask_falloff` at the point's pixel (a source that sees its background there blends little), as
    ``finetune --source-masks`` scores real object captures (:func:`masks_hold_scene`: DTU). Only for masks that
    hold everything photographed (a procedural scene's masks leave out its ground); the web viewer does it too (the
    masks in its images' alpha channel: :func:`omnirecon.viewer.bundle.mask_table`)."""
    soften: float = 0.0
    """Blur the colour at the mesh's depth edges by a Gaussian of this many pixels (0: off;
    :func:`omnirecon.render.edges.soften_edges`), as ``finetune --soften`` scores (its record's ``"soften"``:
    :func:`realtime_setting`); ``python -m bench realtime_blend`` checks it scores what finetune scores
    (BENCHMARKS "Real-time mesh path against finetune's scores"). The web viewer does not do it."""
    visibility: bool = False
    """Mask out sources in which the surface point is occluded (a depth test against each source's
    rasterized depth map, computed once per scene). The paper has no such test."""
    visibility_tol: float = 0.01
    """Relative depth tolerance of the occlusion test: occluded when ``z > (1 + tol) * max(4 depths)``."""
    cull_back_faces: bool = True
    """Back-face culling in every rasterization (closed, outward-facing meshes; faster)."""
    backend: Backend = "auto"
    """Rasterizer backend: ``"gl"``, ``"reference"`` (NumPy) or ``"auto"`` (GL when EGL starts)."""
    fused: bool = True
    """Fused appearance branch (same function, faster; Omni-Recon only) instead of ``model.shade``."""
    chunk: int = 32768
    """At most this many surface points per chunk (``K x chunk`` point-view pairs); chunks are equal, as many
    as needed, rounded up to an even number (larger chunks: fewer Python calls per frame, less CPU per frame
    than 8192 at 504x378)."""
    face_budget: int = 0
    """Faces the rasterizer draws at most: a mesh with more is decimated once when the renderer loads it
    (:func:`level_of_detail`: quadric edge collapse); the mesh given (and its file) stay whole. 0: the full mesh (the
    reference path; what ``finetune`` scores). The real-time videos take :data:`REALTIME_FACE_BUDGET`."""
    frame_grid: int = 0
    """With ``blend="angle"``, the frame path (:meth:`MeshRenderer.frame`) first ranks the sources at a grid of the
    frame's pixels, every ``frame_grid`` pixels (at the frame's depth and fill), and each chunk of pixels then ranks
    only its candidates: the union of the ``2 (k + 1)`` nearest framing sources by angle (``k`` = ``angle_sources``) of
    the grid points within ``frame_grid`` rows of it (points no candidate weighs: every source). The work per pixel
    follows the candidates, not every source. 0: every point ranks every source (the reference path; what ``finetune``
    scores). The real-time videos take :data:`REALTIME_FRAME_GRID`."""
    shader: Literal["auto", "torch"] = "auto"
    """How the frame path (:meth:`MeshRenderer.frame`) shades: ``"auto"``, one fragment-shader pass in the GL
    rasterizer's context (:class:`omnirecon.render.glblend.GLBlend`; with ``frame_grid`` and the angle blend, candidate
    sources per tile of ``2 frame_grid`` px) where it applies (GL backend, ``fused``, float32 sources, no ``consensus``,
    at most ``GLBlend.MAX_SOURCES`` sources), else the torch shader; ``"torch"``: the fused torch shader
    (:mod:`omnirecon.mesh.shader`, the GL pass's reference twin). ``python -m bench mesh_lod`` times both."""
    weight_stride: int = 1
    """With the network blend of at most ``GLBlend.STRIDE_SOURCES`` sources, the GL pass (``shader``) runs the
    appearance MLP at every ``weight_stride``-th pixel of each axis only (a pass of its own), and each pixel blends its
    sources with those weights, interpolated bilinearly from the texels on its own surface (z-depth within
    ``GLBlend.WEIGHT_TOL``), over the sources that see it: a level of detail of the shading, chosen per mesh by
    measurement (:func:`omnirecon.engine.lod.choose_level_of_detail`). 1: the MLP at every pixel (the torch shader
    always: its reference)."""
    workers: int = 1
    """Threads that shade the fused shader's chunks side by side (one chunk per thread at a time; torch
    ops release the GIL). With more than 1, set torch's intra-op threads to 1 (``torch.set_num_threads``)
    so the two kinds of parallelism do not oversubscribe the cores: ``omnirecon bench --threads N`` does."""


def scene_blend(rig: str, masks: bool, background: bool) -> tuple[str, str]:
    """The mesh path's default ``(blend, fill)`` per scene kind (``finetune --blend auto --fill auto``, the
    real-time renders of ``demo`` / ``reconstruct`` and the viewer's start): ``rig`` (``"object"`` or
    ``"forward"``), whether the scene has object ``masks``, whether its ``background`` colour is known
    (procedural scenes). Chosen at ``finetune``'s ``--nearest 6``, held-out, before tuning (``python -m bench
    depth_sources``, BENCHMARKS "Depth sources"):

    * real object captures (no known background colour), with masks (DTU) or without (a user's photos): the angle
      blend and the nearest fill, which beat the network blend and the far layer on DTU, fox and ethiopianHead
      meshed without its masks;
    * a known background colour (procedural scenes): the network's blend and that colour (the nearest fill paints
      the sky beside the objects; the angle blend scores a little higher on the demo but leaves ``finetune``
      nothing to tune, so it is not the default there);
    * otherwise (forward-facing scenes such as fern): the network's blend and the far layer. (``masks`` no longer
      changes the choice.)"""
    kind = SceneKind(rig, masks, background)
    return kind.blend, kind.fill


def masks_hold_scene(scene) -> bool:
    """The scene's object masks hold everything it photographs (a real object capture with masks, DTU: an object
    rig, masks, no known background colour), so a source pixel off its mask shows background, never surface: where
    the angle blend weighs sources by :func:`mask_falloff` (``finetune --source-masks``,
    ``MeshRenderOptions.source_masks``)."""
    return scene_kind(scene).source_masks


REALTIME_SOURCES = 6
"""Source views per frame of the real-time mesh path's network blend when no ``finetune`` record says otherwise:
``finetune --nearest``'s default (each view blends its 6 nearest sources). The angle blend takes every training view
(``"sources": 0``), each point its nearest among them, as finetune scores it: with 6 sources per frame the held-out
DTU views scored below finetune, with every source as finetune does, at more CPU per frame; the fused shader tests
occlusion and samples colours at each point's nearest sources only (:meth:`MeshRenderer._angle_top`), which keeps
that cost down with the same scores (``python -m bench realtime_blend``; BENCHMARKS "Real-time mesh path against
finetune's scores")."""
REALTIME_ANGLE_SOURCES = 4
"""Sources per point of the real-time angle blend when no ``finetune`` record says otherwise: what ``finetune
--angle-sources 3 4 6 8`` chose on its validation views on dtu_scan24 and dtu_scan37."""


def realtime_setting(scene, record: dict | None = None) -> dict:
    """The real-time mesh path's blend for ``scene``: ``finetune``'s record of what it scored with (``curve.json``'s
    ``"render"``: blend, fill, sources per frame (0: every training view), angle sources, source masks, cracks, the blur
    at depth edges) where there is one, else finetune's
    defaults for the scene kind (:func:`scene_defaults`, :data:`REALTIME_SOURCES`, :data:`REALTIME_ANGLE_SOURCES`,
    :func:`masks_hold_scene`, :data:`omnirecon.render.edges.SOFTEN`). One setting, so a video, ``render --mesh`` and the scores blend alike."""
    blend, fill = scene_defaults(scene)
    out = {"blend": blend, "fill": fill, "sources": 0 if blend == "angle" else REALTIME_SOURCES,
           "angle_sources": REALTIME_ANGLE_SOURCES, "source_masks": masks_hold_scene(scene), "cracks": CRACK_RADIUS,
           "soften": SOFTEN}
    scored = (record or {}).get("render") or {}
    for key in ("cracks", "soften"):  # a record from before the crack fill / the softening scored without it
        if scored and key not in scored:
            out[key] = 0
    out.update({k: v for k, v in scored.items() if k in out})
    out["source_masks"] = bool(out["source_masks"]) and masks_hold_scene(scene)
    return out


def realtime_options(setting: dict, **kwargs) -> MeshRenderOptions:
    """:class:`MeshRenderOptions` of a :func:`realtime_setting` (plus ``kwargs``: background, visibility, ...)."""
    return MeshRenderOptions(blend=setting["blend"], fill=setting["fill"], angle_sources=int(setting["angle_sources"]),
                             source_masks=bool(setting["source_masks"]), cracks=int(setting.get("cracks", CRACK_RADIUS)),
                             soften=float(setting.get("soften", 0.0)),
                             weight_stride=int(setting.get("weight_stride", 1)), **kwargs)


def video_options(setting: dict, background, workers: int = 1, face_budget: int | None = None) -> MeshRenderOptions:
    """The real-time videos' :func:`realtime_options` (``reconstruct``'s path, ``demo``'s orbit, ``omnirecon bench
    --realtime``): the occlusion test on, at most ``face_budget`` faces (default :data:`REALTIME_FACE_BUDGET`), each
    chunk's candidate sources (:data:`REALTIME_FRAME_GRID`), ``workers`` shading threads."""
    return realtime_options(setting, background=background, visibility=True, workers=workers,
                            face_budget=REALTIME_FACE_BUDGET if face_budget is None else face_budget,
                            frame_grid=REALTIME_FRAME_GRID)


def scene_defaults(scene) -> tuple[str, str]:
    """:func:`scene_blend` for a loaded scene (``rig``, ``masks``, ``background``). Scenes composited on a known colour
    (procedural ones, Blender's NeRF-synthetic: ``Scene.background`` set) keep the network's blend and that colour."""
    kind = scene_kind(scene)
    return kind.blend, kind.fill


REALTIME_FACE_BUDGET = 200_000
"""Faces the real-time videos (``reconstruct``'s path, ``demo``'s orbit: :func:`omnirecon.workflows.render.mesh_path_video`)
and ``omnirecon bench --realtime`` draw at most (``MeshRenderOptions.face_budget``), chosen by ``python -m bench mesh_lod``
(frame time and held-out PSNR against the full mesh per budget; BENCHMARKS "Real-time mesh path: level of detail and
candidate sources")."""

REALTIME_FRAME_GRID = 16
"""``MeshRenderOptions.frame_grid`` of the real-time videos and ``omnirecon bench --realtime`` (``python -m bench
mesh_lod``: frame time and held-out PSNR against every source ranked at every point)."""


SEEN_SUPERSAMPLE = 4
""":func:`photographed_faces` looks for each face at this many samples per pixel along each axis of the photos: a face
smaller than a pixel on a surface a photo sees falls between the pixel centres, but seldom between all of these samples
(and one smaller than :data:`SEEN_MIN_SAMPLES` of them is drawn anyway)."""
SEEN_MIN_SAMPLES = 4.0
""":func:`photographed_faces` judges a face only where some photo frames it over at least this many samples (its
projected area in samples of the :data:`SEEN_SUPERSAMPLE` grid): a smaller face may fall between the samples however it
lies, and is drawn."""
SEEN_MAX_SIDE = 4096
""":func:`photographed_faces` rasterizes a photo at most this many pixels on its long side (fewer samples per pixel on
larger photos)."""


def photographed_faces(vertices, faces, cameras: Cameras, supersample: int = SEEN_SUPERSAMPLE,
                       backend: Backend = "auto") -> np.ndarray:
    """The faces a renderer of the photos ``cameras`` needs: those some photo sees (the nearest face at some of
    ``supersample`` x ``supersample`` samples of a pixel, back faces culled as the mesh path draws), and those no photo
    shows large enough to judge (under :data:`SEEN_MIN_SAMPLES` samples in every photo that has it in front, within its
    image). The others lie behind the surfaces every photo sees (completion's fills of one view hidden from all,
    coplanar copies losing the depth test) or face away from every photo. ``vertices # [V, 3]``, ``faces # [F, 3]``;
    ``# [F]`` bool"""
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces)
    seen = np.zeros(len(faces), bool)
    largest = np.zeros(len(faces))  # [F] the most samples a photo spreads each face over
    if not len(faces):
        return seen
    with MeshRasterizer(vertices, faces, backend=backend) as rasterizer:
        for i in range(len(cameras)):
            cam = cameras[i]
            scale = max(1, min(supersample, SEEN_MAX_SIDE // max(cam.width, cam.height)))
            ids = rasterizer.face_ids(cam.rescaled(scale) if scale > 1 else cam)  # [H s, W s], -1: background
            seen[ids[ids >= 0]] = True
            c64 = cam.to(device="cpu", dtype=torch.float64)
            K, w2c = c64.K[0].numpy(), c64.w2c[0].numpy()
            p = vertices @ w2c[:3, :3].T + w2c[:3, 3]  # [V, 3] camera frame
            uv = ((p @ K.T)[:, :2] / np.maximum(p[:, 2:], 1e-9))[faces]  # [F, 3, 2] pixels
            e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
            area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) * scale ** 2  # [F] in samples
            c = uv.mean(1)
            framed = (p[faces, 2].min(1) > 0) & (c[:, 0] >= 0) & (c[:, 1] >= 0) & (c[:, 0] < cam.width) & \
                (c[:, 1] < cam.height)
            largest = np.maximum(largest, np.where(framed, area, 0.0))
    return seen | (largest < SEEN_MIN_SAMPLES)


def level_of_detail(mesh, budget: int, photos: Cameras | None = None,
                    decimator: str = "fast") -> tuple[np.ndarray, np.ndarray]:
    """The ``(vertices # [V, 3], faces # [F, 3])`` a renderer draws of ``mesh`` (a ``trimesh.Trimesh`` or such a pair):
    at most ``budget`` faces (its coincident vertices welded, :func:`omnirecon.mesh.clean.weld`, then quadric edge
    collapse, :func:`omnirecon.mesh.clean.decimate` with ``decimator``), the mesh itself when it fits or ``budget`` is
    0. Welding first lets the collapse merge completion's pixel fills into the surfaces they continue; unwelded, each
    pixel's quad is a border of its own and the collapse deletes them (``python -m bench mesh_lod``, BENCHMARKS
    "Real-time mesh path: level of detail and candidate sources").

    With ``photos``, only the faces those cameras see (:func:`photographed_faces`) are drawn: the depth pass shades every
    fragment of every face in the frame, hidden or not, and on completed meshes most of those fragments were on faces no
    photo sees (BENCHMARKS "Real-time mesh path: level of detail and candidate sources"). Where a frame sees past the photographed surface, the
    renderer's fill shades the pixel instead (:class:`MeshRenderOptions` ``fill``, ``cracks``). The faces are the mesh's,
    never moved; its vertices are all kept."""
    vertices, faces = (mesh.vertices, mesh.faces) if hasattr(mesh, "faces") else mesh
    if 0 < budget < len(faces):
        import trimesh

        from omnirecon.mesh.clean import decimate, weld

        small = decimate(trimesh.Trimesh(*weld(vertices, faces), process=False), budget, decimator)
        vertices, faces = np.asarray(small.vertices), np.asarray(small.faces)
    if photos is None:
        return vertices, faces
    faces = np.asarray(faces)
    return vertices, faces[photographed_faces(np.asarray(vertices), faces, photos)]


class MeshRenderer(SourceShader):
    """Renders a mesh from any camera with Omni-Recon's appearance branch and cached source features.

    Args:
        model: An :class:`~omnirecon.models.omnirecon.OmniRecon` (with ``options.fused=False``,
            anything with ``encode`` and ``shade(features, points, origins, visible)``). It is put in
            eval mode and run without gradients.
        mesh: A ``trimesh.Trimesh`` or a ``(vertices # [V, 3], faces # [F, 3])`` pair, in the sources'
            world frame.
        sources: The source views (images, cameras, near/far, bounds), on the model's device.
        options: :class:`MeshRenderOptions`.
    """

    def __init__(self, model, mesh, sources: Sources, options: MeshRenderOptions | None = None,
                 shared: tuple[ViewCache, list[int]] | None = None):
        self.options = options or MeshRenderOptions()
        self.model = model.eval()
        self._shared = shared
        """``(cache, views)``: built by :meth:`ViewCache.renderer` for the scene views ``views`` (``sources``); the
        rasterizer, each view's occlusion depths and mask falloff and the encoding come from (and stay with) the cache."""
        if shared is None:
            vertices, faces = level_of_detail(mesh, self.options.face_budget)
            self.rasterizer = MeshRasterizer(vertices, faces, backend=self.options.backend,
                                             cull_back_faces=self.options.cull_back_faces)
            """The rasterizer: one GL context and the uploaded mesh, reused by every frame."""
        else:
            self.rasterizer = shared[0].rasterizer
        self.sources = sources
        self.dtype = sources.images.dtype
        self.device = sources.images.device
        self.num_views = len(sources.cameras)
        with torch.inference_mode():
            encode = getattr(model, "encode_appearance", model.encode)  # the volume is never read here
            self.features = encode(sources) if shared is None else shared[0].features(shared[1], encode)
            """The encoded sources (once per scene; :meth:`ViewCache.features`: once per set of views)."""
            self._setup_sources(model, sources)
        self._pool = ThreadPoolExecutor(self.options.workers) if self.options.workers > 1 and self.options.fused else None
        self._gl: GLBlend | bool | None = None  # the frame path's GL pass (False: it does not apply; _gl_blend)
        self._centres: dict[tuple[int, int], Tensor] = {}
        self.mask_falloff: Tensor | None = None
        """With the angle blend and ``options.source_masks``, sources that carry masks: :func:`~omnirecon.mesh.kernel.mask_falloff`.
        ``# [K, H, W]``"""
        if self.options.blend == "angle" and self.options.source_masks and sources.masks is not None:
            self.mask_falloff = (mask_falloff(sources.masks) if shared is None else
                                 shared[0].per_view("falloff", shared[1], lambda k: mask_falloff(sources.masks[k:k + 1])))
            self.mask_falloff = self.mask_falloff.to(self.device, self.dtype)
        self.source_depth_max: Tensor | None = None
        """With ``options.visibility``: per source, the largest rasterized depth of each 2x2 block of
        pixel centres (inf = background or outside), ``# [K, H + 1, W + 1]``; entry ``(a, b)`` covers
        rows ``a - 1, a`` and columns ``b - 1, b``."""
        if self.options.visibility:
            self.source_depth_max = block_depth_max(self.source_depths().to(self.device, self.dtype)) if shared is None \
                else shared[0].per_view("depth_max", shared[1], lambda k: block_depth_max(
                    self.rasterizer.depth(sources.cameras[k])[None].to(self.device, self.dtype)))
        with torch.inference_mode():
            self._gl_blend()  # built here, not in a timed frame

    def source_depths(self) -> Tensor:
        """Rasterized z-depth of the mesh at every source camera, 0 = background (the depth pass). ``# [K, H, W]``"""
        cams = self.sources.cameras
        return torch.stack([self.rasterizer.depth(cams[i]).clone() for i in range(len(cams))])

    # ------------------------------------------------------------------ per point
    def weights(self, camera: Cameras, with_rgb: bool = False, with_coords: bool = True, fill: bool = False) -> ShadeResult:
        """Rasterize ``camera`` (one camera) and compute the blend weights of its covered pixels
        (with ``with_rgb``, also their blended source colour; ``with_coords=False`` skips storing the
        source coordinates that :meth:`blend` needs; with ``fill``, every other pixel too, on the
        background layer of :func:`omnirecon.mesh.fill.with_fill`)."""
        with torch.inference_mode():
            surf, covered, layer = self.rasterizer.surface(camera), None, None
            if fill or self.options.cracks > 0:
                surf, covered, layer = shaded_surface(surf, camera, self.sources.far,
                                                      layer_box(self.sources.rig, self.sources.bounds),
                                                      self.options.fill if fill else "background", self.options.cracks)
                layer = layer.to(self.device)
            points = surf.points.to(self.device, self.dtype)  # [P, 3]
            origin = camera.centers[0].to(self.device, self.dtype)  # [3]
            on_mesh = None if covered is None else (torch.arange(len(surf.pixels)) < covered).to(self.device)  # [P]
            if self.options.fused:
                return replace(self._fused(surf, points, origin, with_rgb, with_coords, layer, on_mesh), covered=covered)
            shaded = ShadeResult(surf, *self._plain_points(points, origin, layer, on_mesh, with_rgb), covered)
            return replace(shaded, rgb=self.blend(shaded, self._rgb)) if with_rgb and shaded.rgb is None else shaded

    def _run_chunks(self, fn, total: int) -> None:
        """``fn(slice)`` over ``range(total)`` in equal chunks of at most ``options.chunk``, on the worker
        threads when there are several (each chunk writes its own slice of the outputs). The number of
        chunks is even, so two workers never wait on a last short chunk, and does not depend on the
        workers, so neither does the image (bit for bit)."""
        count = -(-total // self.options.chunk)
        count += count % 2
        size = max(1, -(-total // max(count, 1)))

        def one(s: int) -> None:
            with torch.inference_mode():  # thread-local: the pool's threads need it too
                fn(slice(s, min(s + size, total)))

        starts = range(0, total, size)
        if self._pool is None or len(starts) < 2:
            for s in starts:
                one(s)
        else:
            list(self._pool.map(one, starts))  # list(): waits, and raises a worker's error here

    def _fused(self, surf: Surface, points: Tensor, origin: Tensor, with_rgb: bool, with_coords: bool,
               layer: Tensor | None = None, on_mesh: Tensor | None = None) -> ShadeResult:
        """``OmniRecon.shade`` for one point per pixel, fused (module docstring); ``layer``, ``on_mesh`` ``# [P]`` bool:
        the points on the fill's far layer, on the mesh (:meth:`~omnirecon.mesh.shader.SourceShader._shade_points`)."""
        K, total = self.num_views, points.shape[0]
        new = dict(dtype=self.dtype, device=self.device)
        omega = torch.empty(K, total, **new)
        coords = torch.empty(K, 2, total, **new) if with_coords else None
        mask_all = torch.empty(K, total, dtype=torch.bool, device=self.device)
        rgb = torch.empty(3, total, **new) if with_rgb else None

        def shade(sl: slice) -> None:
            p = points[sl].T.contiguous()  # [3, n]
            om, mask, st, c = self._shade_points(p, p - origin[:, None], with_rgb, with_coords,
                                                 None if layer is None else layer[sl],
                                                 None if on_mesh is None else on_mesh[sl])
            omega[:, sl], mask_all[:, sl] = om, mask
            if with_coords:
                coords[:, :, sl] = st
            if with_rgb:
                rgb[:, sl] = c

        self._run_chunks(shade, total)
        return ShadeResult(surf, omega, mask_all, coords, None if rgb is None else rgb.T)

    def _pixel_centres(self, width: int, height: int) -> Tensor:
        """Pixel centres ``(j + 0.5, i + 0.5)`` of a ``width x height`` image, row-major. ``# [2, H W]``"""
        key = (width, height)
        if key not in self._centres:
            u = torch.arange(width, dtype=self.dtype, device=self.device) + 0.5
            v = torch.arange(height, dtype=self.dtype, device=self.device) + 0.5
            self._centres[key] = torch.stack([u.repeat(height), v.repeat_interleave(width)])
        return self._centres[key]

    def frame(self, camera: Cameras) -> Tensor:
        """The colour of one view, the fast way (what :meth:`render` with ``extras=False`` returns):
        ``rgb # [H, W, 3]``.

        The rasterizer draws only the z-depth (:meth:`MeshRasterizer.depth`); each chunk of pixels, in
        row-major order and on the worker threads, then unprojects its pixel centres to surface points
        ``origin + z d(u, v)`` (``d`` at camera z = 1, :func:`~omnirecon.mesh.fill.ray_basis`), puts the
        fill's background layer where the mesh misses (``z`` where the ray leaves the bounds,
        :func:`~omnirecon.mesh.fill.exit_depth`) or leaves the background colour there, shades them and
        writes its rows of the image: no compaction, no scatter and no serial fill. Its reference twin is
        :meth:`render` with ``extras=True`` (rasterized world points, :func:`~omnirecon.mesh.fill.with_fill`,
        :meth:`Surface.image`); fused shader only."""
        gl = self._gl_blend()
        if gl is not None:
            return self._gl_frame(gl, camera)
        H, W = camera.height, camera.width
        depth = self.rasterizer.depth(camera)  # [H, W]; 0 = background
        mesh_z = depth  # [H, W] the mesh's own depth (no fill): its depth edges are softened
        hit = (depth > 0).reshape(-1).to(self.device) if self.mask_falloff is not None else None  # [H W] on the mesh
        if self.options.fill == "nearest" or self.options.cracks > 0:  # one distance transform a frame, before the chunks
            reach = NEAREST_FILL_REACH if self.options.fill == "nearest" else 0.0
            depth = torch.from_numpy(nearest_depth(depth.float().cpu().numpy(), reach, self.options.cracks))
        depth = depth.reshape(-1).to(self.device, self.dtype)  # [H W]
        A, origin = (t.to(self.device, self.dtype) for t in ray_basis(camera))  # [3, 3], [3]
        A2, Auv, o = A[2][:, None], A[:2].T.contiguous(), origin[:, None]  # [3, 1], [3, 2], [3, 1]
        centres = self._pixel_centres(W, H)
        out = torch.empty(H * W, 3, dtype=self.dtype, device=self.device)
        fill = self.options.fill != "background"
        background = torch.tensor(self.options.background, dtype=self.dtype, device=self.device)
        far, bounds = self.sources.far, layer_box(self.sources.rig, self.sources.bounds)
        shader = self._frame_sources(depth, (H, W), origin, lambda pix: torch.addmm(A2, Auv, centres[:, pix]),
                                     (lambda d: exit_depth(d, origin, far, bounds)) if fill else None)

        def shade(sl: slice) -> None:
            z = depth[sl]  # [n]
            d = torch.addmm(A2, Auv, centres[:, sl])  # [3, n]: the ray through each pixel centre, camera z = 1
            target = out[sl]  # [n, 3] (a view)
            hole = z <= 0
            keep, layer, on_mesh = None, None, None if hit is None else hit[sl]
            if bool(hole.any()):
                miss = hole.nonzero()[:, 0]
                if fill:
                    z = z.clone()
                    z[miss] = exit_depth(d[:, miss], origin, far, bounds)
                    layer = hole  # the far layer skips the occlusion test (weights())
                else:
                    target[miss] = background
                    keep = (~hole).nonzero()[:, 0]
                    if not len(keep):
                        return
                    d, z = d[:, keep], z[keep]
                    on_mesh = None if on_mesh is None else on_mesh[keep]
            p = torch.addcmul(o, d, z[None])  # [3, n] surface points
            rgb = shader(sl)._shade_points(p, d, True, layer=layer, on_mesh=on_mesh, with_mask=False)[3]  # [3, n]
            if keep is None:
                target.copy_(rgb.T)
            else:
                target[keep] = rgb.T

        with torch.inference_mode():
            self._run_chunks(shade, H * W)
            return soften_edges(out.reshape(H, W, 3), mesh_z, self.options.soften)

    def _gl_blend(self) -> GLBlend | None:
        """The frame path's GL pass (``MeshRenderOptions.shader``), built once; ``None`` where it does not apply (the
        torch shader then shades)."""
        o = self.options
        if self._gl is None:
            self._gl = False
            if (o.shader == "auto" and o.fused and self.rasterizer.context is not None and self.dtype == torch.float32
                    and not (o.blend == "angle" and o.consensus > 0) and self.num_views <= GLBlend.MAX_SOURCES):
                K, angle = self.num_views, o.blend == "angle"
                net = {}
                if not angle:
                    w1z, w1d, b1, w2, b2, w3, b3 = self._mlp  # [C, h1], [3, h1], [h1], [h2, h1], [h2, 1], [1, h2], [1, 1]
                    a = self._feat  # the folded maps, bordered by b: its first K (h + 2) (w + 2) texel rows
                    net = dict(mlp=[torch.cat([w1z, w1d]).T, b1, w2, b2, w3, b3],
                               features=a.rows[:K * (a.h + 2) * (a.w + 2)].reshape(K, a.h + 2, a.w + 2, a.C).permute(0, 3, 1, 2))
                self._gl = GLBlend(self.rasterizer.context, self.sources.images, self._proj.reshape(K, 3, 4),
                                   self._centers_t, o.angle_sources if angle else None, self.source_depth_max,
                                   o.visibility_tol, self.mask_falloff if angle else None, **net,
                                   stride=o.weight_stride)
        return self._gl or None

    def _gl_frame(self, gl: GLBlend, camera: Cameras) -> Tensor:
        """:meth:`frame` through the GL pass: the depth pass, the nearest/crack fill on the CPU, one fragment-shader pass
        (:meth:`GLBlend.shade`), the blur at depth edges. ``# [H, W, 3]``"""
        return self._gl_finish(gl, *self._gl_submit(gl, camera))

    def _gl_submit(self, gl: GLBlend, camera: Cameras, drawn=None) -> tuple:
        """:meth:`_gl_frame` up to the GL pass, drawn and handed to llvmpipe's threads (:meth:`GLBlend.submit`): the
        depth pass (or ``drawn()``: its :meth:`MeshRasterizer.depth_ahead`), the fill, the candidates. Returns what
        :meth:`_gl_finish` takes."""
        depth_pass = self.rasterizer.depth(camera) if drawn is None else drawn()
        mesh_z = depth_pass.clone()  # [H, W]; 0 = background (off the rasterizer's host buffer)
        depth = mesh_z.numpy()
        if self.options.fill == "nearest" or self.options.cracks > 0:
            depth = nearest_depth(depth, NEAREST_FILL_REACH if self.options.fill == "nearest" else 0.0, self.options.cracks)
        A, origin = ray_basis(camera)
        far, box = self.sources.far, layer_box(self.sources.rig, self.sources.bounds)
        size = gl.submit(depth, mesh_z.numpy() > 0, A, origin, self.options.fill != "background",
                         self.options.background, far, box, self.options.frame_grid, lambda d: exit_depth(d, origin, far, box))
        return size, mesh_z

    def _gl_finish(self, gl: GLBlend, size: tuple[int, int, int], mesh_z: Tensor) -> Tensor:
        """The GL pass's colour of a :meth:`_gl_submit` read back, blurred at depth edges. ``# [H, W, 3]``"""
        rgb = gl.result(*size).to(self.device, self.dtype, copy=True)  # [H, W, 3] off the pass's reused host buffer
        with torch.inference_mode():
            return soften_edges(rgb, mesh_z.to(self.device), self.options.soften)

    def frames(self, cameras) -> Iterator[Tensor]:
        """:meth:`frame` of each camera of ``cameras`` (an iterable of one-camera batches), the same images bit for bit,
        ``# [H, W, 3]`` each. Through the GL pass a frame ahead: while llvmpipe's threads shade one frame, this thread
        draws the next one's depth pass (the passes' front end runs on this thread); while they rasterize that, it
        reads back and blurs the frame before (and the caller takes it), so on idle cores a stream of frames takes
        less wall time than one :meth:`frame` after another."""
        gl = self._gl_blend()
        pending = None
        for camera in cameras:
            if gl is None:
                yield self.frame(camera)
                continue
            drawn = self.rasterizer.depth_ahead(camera)
            if pending is not None:
                yield self._gl_finish(gl, *pending)
            pending = self._gl_submit(gl, camera, drawn)
        if pending is not None:
            yield self._gl_finish(gl, *pending)

    # ------------------------------------------------------------------ images
    def blend(self, shaded: ShadeResult, signal: Tensor | TexelAtlas) -> Tensor:
        """Blend a per-view ``signal # [K, C, H', W']`` (channel-first, or a border-padded
        :class:`~omnirecon.mesh.atlas.TexelAtlas`) at ``shaded``'s points with its weights (bilinear, border padding). ``# [P, C]``"""
        atlas = signal if isinstance(signal, TexelAtlas) else TexelAtlas(signal.to(self.device, self.dtype), "border")
        K, C = atlas.K, atlas.C
        out = torch.empty(shaded.omega.shape[1], C, dtype=self.dtype, device=self.device)
        for s in range(0, out.shape[0], self.options.chunk):
            sl = slice(s, s + self.options.chunk)
            values = atlas.sample(*atlas.taps(shaded.coords[:, :, sl])).reshape(K, -1, C)
            out[sl] = (values * shaded.omega[:, sl, None]).sum(0)
        return out

    def render(self, camera: Cameras, extras: bool = True) -> dict[str, Tensor]:
        """Render one view: ``rgb # [H, W, 3]`` (where no triangle: the options' fill) and, with
        ``extras``, ``depth # [H, W]`` (z-depth, 0 = background), ``mask # [H, W]`` (covered by the
        mesh; its mean is the view's coverage), ``blend # [H, W, K]`` (omega, 0 on background) and
        ``seen # [H, W]`` (some source sees the surface point)."""
        if not extras and self.options.fused:
            return {"rgb": self.frame(camera)}
        with torch.inference_mode():
            shaded = self.weights(camera, with_rgb=True, with_coords=not self.options.fused,
                                  fill=self.options.fill != "background")
            rgb = shaded.rgb if shaded.rgb is not None else self.blend(shaded, self._rgb)
            rgb = shaded.surface.image(rgb, self.options.background)
            out = self._outputs(shaded, rgb=rgb)
            out["rgb"] = soften_edges(rgb, out["depth"], self.options.soften)  # the mesh's depth (0: fill)
            return out if extras else {"rgb": out["rgb"]}

    def render_signal(self, camera: Cameras, signal: Tensor, background: float | Tensor = 0.0) -> dict[str, Tensor]:
        """Render a per-view signal ``# [K, H', W', C]`` (any resolution covering each source image)
        with the colour's weights. Returns ``signal # [H, W, C]`` (``background`` where no triangle)
        plus the extras of :meth:`render`."""
        if signal.dim() != 4 or signal.shape[0] != self.num_views:
            raise ValueError(f"signal must be [K={self.num_views}, H, W, C], got {tuple(signal.shape)}")
        with torch.inference_mode():
            shaded = self.weights(camera)
            values = self.blend(shaded, signal.permute(0, 3, 1, 2))
            return self._outputs(shaded, signal=shaded.surface.image(values, background))

    def _outputs(self, shaded: ShadeResult, **images: Tensor) -> dict[str, Tensor]:
        surf = shaded.surface
        covered = torch.ones(len(surf.pixels), 1, dtype=self.dtype, device=self.device)
        if shaded.covered is not None:
            covered[shaded.covered:] = 0
        return {**images,
                "depth": surf.image(surf.depth[:, None].to(self.device, self.dtype) * covered, 0.0)[..., 0],
                "mask": surf.image(covered, 0.0)[..., 0] > 0,
                "blend": surf.image(shaded.omega.T, 0.0),
                "seen": surf.image(shaded.mask.any(0)[:, None].to(self.dtype), 0.0)[..., 0] > 0}

    def close(self) -> None:
        """Free the rasterizer's GL context (and the shading threads); a :meth:`ViewCache.renderer`'s rasterizer stays
        open with its cache."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        if self._gl:
            self._gl.close()
        self._gl = None
        if self._shared is None:
            self.rasterizer.close()

    def __enter__(self) -> MeshRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
