"""Real-time image-based mesh rendering with Omni-Recon's appearance branch (``shared/docs/omnirecon.md`` §7).

Per frame: rasterize the mesh at the target camera (:mod:`omnirecon.render.raster`) -> one surface
point per covered pixel -> the appearance branch blends the source views there
(``omega = softmax_i MLP([ReLU(Linear(F_i(x))); u - u_i])``, colour ``sum_i omega_i c_i``) ->
background colour elsewhere. The geometry branch and the feature volume are neither used nor computed, and the
source features are encoded once per scene by :class:`MeshRenderer`, not per frame.

**Visibility** (not in the paper). With ``MeshRenderOptions.visibility`` the mesh is rasterized at
every source camera once, and source ``i`` is masked out of a point's blend when the point is
*occluded* there: its z-depth in source ``i`` exceeds ``(1 + visibility_tol)`` times the largest of
the four rasterized depths around its projection (the bilinear footprint; background and outside
the image count as infinitely far). Taking the largest of the four makes the test one-sided and
safe on the point's own surface: on a plane covering the four pixel centres z is convex in the
image, so the largest corner depth is at least the point's own depth; being one-sided, it also keeps
points seen just past an occluder's silhouette. Masked views are treated exactly like views the point
projects outside of (``OmniRecon.shade``'s ``visible`` argument): a point no view sees blends all
views uniformly, as in the volumetric path.

**Fill** (``MeshRenderOptions.fill``, not in the paper): pixels no triangle covers get the background
layer of :mod:`omnirecon.mesh.fill`, shaded by the same blend; ``render``'s ``mask`` is the coverage. With
``fill="nearest"``, those within reach of a covered pixel first take its rendered z-depth
(:func:`omnirecon.mesh.fill.nearest_depth`), as ``finetune --fill nearest`` scores them. Whatever the fill, the missed
pixels the mesh encloses (``MeshRenderOptions.cracks``, :func:`omnirecon.mesh.fill.crack_pixels`) take it too.

**Blend** (``MeshRenderOptions.blend``): ``"network"``, the appearance branch's weights (the paper);
``"angle"``, each point's ``angle_sources`` nearest sources by viewing angle among those that see it, weighted by
angle alone (:func:`angle_weights`, the unstructured lumigraph's blend; no network runs per frame), as
``finetune --blend angle`` scores them; where the sources carry object masks (DTU), each source's weight times
:func:`mask_falloff` at the point's pixel (``MeshRenderOptions.source_masks``). The fused shader samples the colours
of only the ``angle_sources`` sources a point weighs (:meth:`MeshRenderer._sparse_rgb`).

**Sets of sources** (:class:`ViewCache`): frames that each blend their own nearest sources (videos, as ``finetune
--nearest`` scores) share one rasterizer, each view's occlusion depths and mask falloff, and one encoding per set
of views; the encoding cannot be shared per view, as the encoder normalises with the batch statistics of the views
it encodes together. The renderer encodes the appearance maps only (``OmniRecon.encode_appearance``: no volume).

**Signals.** The same weights render any per-view signal (:meth:`MeshRenderer.render_signal`,
:func:`render_signal`): a ``[K, H', W', C]`` tensor (e.g. 2-D predictions to lift into 3-D), sampled
like the source RGB (bilinear, border padding, at any resolution covering the source images) and
blended with ``omega``.

**Fused shader** (``MeshRenderOptions.fused``, the default): the same function as
``OmniRecon.shade`` with less work per frame (tests: equal to float tolerance). Per scene, the
appearance projection is applied to the feature maps (``W F_i + b``; bilinear sampling is linear and
its weights sum to 1, so sampling that map equals ``W f + b``; the map's zero padding becomes a
border of ``b``), and the ``K`` maps become one texel table sampled with ``embedding_bag`` (a
weighted sum of 4 rows: several times faster than ``grid_sample`` for 16 channels on the CPU). Per frame,
points go through in chunks; where fewer than two sources see a point its weights need no network
(one source: weight 1 exactly, as the softmax gives against the others' ``-1e9`` logits; none: ``1 / K``
each), so only the other points are compacted and shaded; every MLP layer is one matrix product over all
``K x n`` point-view pairs (layers 2 and 3 column-major: several times faster than row-major for these narrow
layers), and the source colours are sampled exactly as the model does. ``fused=False`` calls
``model.shade`` (any model with ``encode`` and ``shade``). With ``MeshRenderOptions.workers`` > 1, chunks
are shaded by that many threads at once (each writes its own slice of the outputs): on 2 cores with one
torch thread this parallelises every op of a chunk, where torch's intra-op threads split only the ops
above its grain size.

**Frame path** (:meth:`MeshRenderer.frame`, what ``render(extras=False)`` returns): the rasterizer draws
only the z-depth, and each chunk of pixels, in row-major order on the worker threads, unprojects its
pixel centres, puts the fill's layer where the mesh misses, shades and writes its rows of the image, so
nothing but the depth pass runs on one thread. Its reference twin is ``render()`` (rasterized world points,
fill and scatter). ``python -m bench mesh_fps --size 504 378 --threads 1``: 63.7 ms of CPU per frame before
this path and the network skip, 47.8 after (336x252: 32.6 -> 24.3).

**Level of detail and candidate sources** (the real-time videos, ``omnirecon bench --realtime``). With
``MeshRenderOptions.face_budget`` the renderer draws the mesh decimated once to that many faces
(:func:`level_of_detail`; the depth pass on llvmpipe costs about linearly in the faces drawn); with ``frame_grid`` the
angle blend's frame path ranks, per chunk of pixels, only the sources a grid of the frame's pixels near it ranks
among its nearest (:meth:`MeshRenderer._frame_sources`), instead of every source at every pixel; points no candidate
weighs fall back to every source. Both default to off: the full mesh and every source are the reference path they are
measured against (``python -m bench mesh_lod``).

Size: the renderer, its fused shader and the texel atlas the shader samples are one real-time path,
timed and tested together (the fill's geometry is in :mod:`omnirecon.mesh.fill`).
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.mesh.fill import (
    CRACK_RADIUS,
    NEAREST_FILL_REACH,
    exit_depth,
    layer_box,
    nearest_depth,
    ray_basis,
    shaded_surface,
)
from omnirecon.rays import Sources
from omnirecon.render.edges import SOFTEN, soften_edges
from omnirecon.render.raster import Backend, MeshRasterizer, Surface
from omnirecon.scene_kind import SceneKind, scene_kind


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
    :func:`angle_weights` over the ``angle_sources`` sources nearest by viewing angle that see it."""
    angle_sources: int = 4
    """With ``blend="angle"``: sources blended per point (0: every source that sees it); ``finetune --angle-sources``
    (:data:`REALTIME_ANGLE_SOURCES`)."""
    consensus: float = 0.0
    """With ``blend="angle"``: :func:`consensus_weights`' width in RGB (0: off); ``finetune --consensus``."""
    source_masks: bool = False
    """With ``blend="angle"`` and sources that carry object masks (``Sources.masks``): each source's weight times
    :func:`mask_falloff` at the point's pixel (a source that sees its background there blends little), as
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
    workers: int = 1
    """Threads that shade the fused shader's chunks side by side (one chunk per thread at a time; torch
    ops release the GIL). With more than 1, set torch's intra-op threads to 1 (``torch.set_num_threads``)
    so the two kinds of parallelism do not oversubscribe the cores: ``omnirecon bench --threads N`` does."""


@dataclass
class ShadeResult:
    """Blend weights of the covered pixels of one frame (``P`` pixels, ``K`` sources)."""

    surface: Surface
    """The covered pixels, their surface points and depths (CPU)."""
    omega: Tensor
    """Blend weight of each source at each covered pixel (sums to 1 over sources). ``# [K, P]``"""
    mask: Tensor
    """Source ``k`` sees the point: in front, inside its image and (with the visibility test) not
    occluded. ``# [K, P]`` bool"""
    coords: Tensor | None
    """Projection of each point into each source as a fraction of the image size, ``(u / W, v / H)``
    (inside the image: ``[0, 1)``); what :meth:`MeshRenderer.blend` samples signals at (``None`` when
    only the colour was asked for). ``# [K, 2, P]``"""
    rgb: Tensor | None = None
    """Blended source colour, when the shader computed it on the way. ``# [P, 3]``"""
    covered: int | None = None
    """The first ``covered`` pixels lie on the mesh, the rest on the fill's background layer
    (``None``: every pixel is on the mesh)."""


class TexelAtlas:
    """``K`` channel-first maps ``# [K, C, h, w]`` as one row table for bilinear sampling with
    :func:`torch.nn.functional.embedding_bag` (a weighted sum of 4 rows per sample, one call for all
    ``K`` maps).

    ``padding="zeros"`` adds a one-texel border of ``pad_value # [C]`` (default 0) around each map:
    taps outside a map read it, as ``grid_sample(padding_mode="zeros")`` does for 0 (samples must lie
    inside the image or be masked out). ``"border"`` clamps texel coordinates to the map, as
    ``padding_mode="border"``. Both match ``grid_sample(..., align_corners=False)`` up to the float
    rounding of the coordinates. The bilinear weights of a sample sum to 1; masked samples read 0.
    """

    def __init__(self, maps: Tensor, padding: str = "zeros", pad_value: Tensor | None = None):
        if padding not in ("zeros", "border"):
            raise ValueError(f"padding must be 'zeros' or 'border', got {padding!r}")
        self.padding = padding
        """``"zeros"`` or ``"border"``."""
        self.K, self.C, self.h, self.w = maps.shape
        p = 1 if padding == "zeros" else 0
        if p and pad_value is not None:
            value = pad_value.to(maps).reshape(1, -1, 1, 1)
            maps = F.pad(maps - value, (p, p, p, p)) + value
        else:
            maps = F.pad(maps, (p, p, p, p))
        self._row_len = self.w + 2 * p
        self._zero_row = self.K * (self.h + 2 * p) * self._row_len
        rows = maps.permute(0, 2, 3, 1).reshape(-1, self.C)
        # zero tail: taps one past a map's last texel (weight 0), and masked samples, stay in the table
        self.rows = torch.cat([rows, rows.new_zeros(self._row_len + 2, self.C)]).contiguous()
        """The texels, map-major then row-major, then a zero tail. ``# [K (h + 2p) (w + 2p) + w + 2p + 2, C]``"""
        self._map_len = (self.h + 2 * p) * self._row_len
        self._pad = p
        self._index_dtype = torch.float32 if len(self.rows) < 2**24 else torch.float64  # exact integers
        self._scale = torch.tensor([self.w, self.h], dtype=self._index_dtype, device=maps.device)[None, :, None]
        self._hi = self._scale - 1  # largest texel-centre coordinate per axis (border mode)
        self._offsets = torch.tensor([0, 1, self._row_len, self._row_len + 1], device=maps.device)

    def taps(self, coords: Tensor, mask: Tensor | None = None, scale: Tensor | None = None,
             maps: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Rows and weights of the bilinear samples at image fractions ``coords # [K, 2, n]``
        (``u / W, v / H``; map ``k`` for row ``k``, or map ``maps[k, i]`` for sample ``(k, i)`` with
        ``maps # [K, n]`` int64). Samples where ``mask # [K, n]`` is False read 0.
        ``scale # [1, 2, 1]``: texels per unit of ``coords`` instead of the map size (e.g. ``(w / W, h / H)``
        for pixel coordinates). Returns ``index # [K n, 4]`` int64 and ``weight # [K n, 4]``, row-major in ``(k, i)``."""
        K, _, n = coords.shape
        xy = coords.to(self._index_dtype) * (self._scale if scale is None else scale)  # [K, 2, n]
        xy += self._pad - 0.5  # texel-centre coordinates in the padded map
        if self.padding == "border":
            xy.clamp_(min=0)
            xy = torch.minimum(xy, self._hi, out=xy)
        corner = xy.floor()
        frac = (xy - corner).to(coords.dtype)  # [K, 2, n]
        k = (torch.arange(K, device=xy.device)[:, None] if maps is None else maps).to(xy.dtype) * self._map_len
        base = torch.add(corner[:, 0], corner[:, 1], alpha=self._row_len).add_(k).long()  # [K, n]
        if mask is not None:
            base.masked_fill_(~mask, self._zero_row)
        index = base[..., None] + self._offsets  # [K, n, 4]
        rest = 1 - frac
        weight = torch.empty(K, n, 4, dtype=frac.dtype, device=frac.device)  # (y0 x0, y0 x1, y1 x0, y1 x1)
        fx, fy, gx, gy = frac[:, 0], frac[:, 1], rest[:, 0], rest[:, 1]
        torch.mul(gx, gy, out=weight[..., 0])  # strided writes: far faster than a broadcast outer product
        torch.mul(fx, gy, out=weight[..., 1])
        torch.mul(gx, fy, out=weight[..., 2])
        torch.mul(fx, fy, out=weight[..., 3])
        return index.reshape(-1, 4), weight.reshape(-1, 4)

    def sample(self, index: Tensor, weight: Tensor) -> Tensor:
        """Weighted sums of the tapped rows. ``# [K n, C]``"""
        return F.embedding_bag(index, self.rows, per_sample_weights=weight, mode="sum")


def _pick(t: Tensor | None, i: Tensor) -> Tensor | None:
    """``t[i]``, or ``None`` for ``None``."""
    return None if t is None else t[i]


def _norm(d: Tensor) -> Tensor:
    """Euclidean norm over the first axis of ``d # [3, ...]``, clamped like ``F.normalize``. ``# [1, ...]``"""
    sq = d[0] * d[0]
    sq.addcmul_(d[1], d[1]).addcmul_(d[2], d[2])
    return sq.sqrt_().clamp_min_(1e-12)[None]


def block_depth_max(depth: Tensor) -> Tensor:
    """Per source, the largest of the z-depths ``depth # [K, H, W]`` (0 = background: infinitely far) of each
    2x2 block of pixel centres, for :func:`unoccluded`. ``# [K, H + 1, W + 1]``; entry ``(a, b)`` covers rows
    ``a - 1, a`` and columns ``b - 1, b``."""
    d = torch.where(depth > 0, depth, torch.full_like(depth, float("inf")))
    d = F.pad(d[:, None], (1, 1, 1, 1), value=float("inf"))  # [K, 1, H + 2, W + 2]
    return F.max_pool2d(d, 2, stride=1)[:, 0].contiguous()


def unoccluded(dmax: Tensor, uv: Tensor, z: Tensor, tol: float, maps: Tensor | None = None) -> Tensor:
    """The occlusion test (module docstring) of points at source pixel coordinates ``uv # [K, 2, n]`` with
    source z-depths ``z # [K, n]`` against :func:`block_depth_max` ``dmax`` (of source ``k``, or of source
    ``maps[k, i]`` with ``maps # [K', n]`` int64 for ``uv # [K', 2, n]``). ``# [K, n]`` bool"""
    K, Hp, Wp = dmax.shape
    b = torch.floor(uv[:, 0] - 0.5).clamp(-1, Wp - 2).long() + 1  # [K, n] block column
    a = torch.floor(uv[:, 1] - 0.5).clamp(-1, Hp - 2).long() + 1  # [K, n] block row
    flat = ((torch.arange(K, device=uv.device)[:, None] if maps is None else maps) * Hp + a) * Wp + b
    return z <= dmax.reshape(-1)[flat] * (1 + tol)


def angle_weights(points: Tensor, origin: Tensor, centers: Tensor, seen: Tensor, k: int) -> Tensor:
    """Blend weights by viewing angle alone (Buehler et al. 2001, "Unstructured Lumigraph Rendering"; not in the
    paper): at each point, the ``k`` sources that see it (``seen``) whose rays make the smallest angle ``a_i``
    with the target's ray get ``(1 - a_i / a_(k+1)) / a_i`` (``a_(k+1)``: the next source's angle, so weights
    fall to 0 where a source leaves the ``k`` nearest and views change smoothly), normalised to sum 1; a point
    no source sees blends all ``K`` uniformly, as the network path does.

    ``points # [P, 3]``, ``origin # [3]`` (the target camera centre), ``centers # [K, 3]`` (the sources'),
    ``seen # [P, K]`` bool. Returns ``# [P, K]``. On DTU's wide rig this blend beat the appearance network's
    weights over the same visible sources (``finetune --blend angle``, held-out mask PSNR on dtu_scan24 and
    dtu_scan37: BENCHMARKS "Depth sources")."""
    d_t = F.normalize(points - origin, dim=-1)  # [P, 3] target -> point
    d_s = F.normalize(points[:, None] - centers[None].to(points), dim=-1)  # [P, K, 3] sources -> point
    return lumigraph_weights(torch.arccos((d_s * d_t[:, None]).sum(-1).clamp(-1, 1)), seen, k)


def lumigraph_weights(ang: Tensor, seen: Tensor, k: int) -> Tensor:
    """:func:`angle_weights` from the angles ``ang # [P, K]`` (radians) between each source's ray and the target's
    at each point. ``# [P, K]``"""
    ang = torch.where(seen, ang, torch.full_like(ang, float("inf")))
    K = ang.shape[1]
    k = max(1, min(k, K))
    near = ang.topk(min(k + 1, K), dim=1, largest=False).values  # [P, k (+1)] ascending
    thresh = near[:, k:k + 1] if K > k else torch.full_like(near[:, :1], float("inf"))  # [P, 1]
    w = (1 - ang / thresh).clamp_min(0) / ang.clamp_min(1e-3)  # inf angles -> 0
    w = torch.where(ang <= near[:, k - 1:k], w, torch.zeros_like(w))  # the k nearest only
    w = torch.where(torch.isfinite(w), w, torch.zeros_like(w))
    total = w.sum(1, keepdim=True)
    return torch.where(total > 0, w / total.clamp_min(1e-12), torch.full_like(w, 1.0 / K))


MASK_REACH = 2.0
""":func:`mask_falloff`: pixels of a source this far (or farther) inside its object mask keep their full weight."""
MASK_FLOOR = 0.1
""":func:`mask_falloff`: the factor of a source whose pixel lies off its object mask."""


def mask_falloff(masks: Tensor, reach: float = MASK_REACH, floor: float = MASK_FLOOR) -> Tensor:
    """Per source pixel, the factor the angle blend multiplies that source's weight by (not in the paper): its
    distance to the nearest pixel off the object mask ``masks # [K, H, W]`` (bool, True: the object) over ``reach``,
    clamped to ``[floor, 1]`` (off the mask: ``floor``). Only points on the mesh are weighed (the fill's points lie
    off the objects). A surface point whose projection in a source lands on that source's background (DTU's white
    table or black backdrop) or on its object's edge takes the background's colour there: the mesh's silhouette and
    thin parts (handles, blade edges) miss the object's by a pixel or two, and the blend drew a light rim on the brick's
    edges. It raises dtu_scan37's held-out mask PSNR and leaves the whole image as it was; weighing the fill's points
    too lowered the whole image. Reach 1-3 px and floor 0.02-0.2 scored alike; the mesh's own silhouette in each
    source instead of its mask gained less (``python -m bench depth_sources``, the ``, no source masks`` rows;
    BENCHMARKS "Depth sources"). ``# [K, H, W]``"""
    from scipy.ndimage import distance_transform_edt

    m = masks.bool().cpu().numpy()
    dist = np.stack([distance_transform_edt(k) if k.any() else np.zeros(k.shape) for k in m])  # [K, H, W] px
    return torch.from_numpy(np.clip(dist / reach, floor, 1.0)).to(torch.float32)


def mask_factor(falloff: Tensor, uv: Tensor, maps: Tensor | None = None) -> Tensor:
    """:func:`mask_falloff` ``# [K, H, W]`` at source pixel coordinates ``uv # [K, 2, n]`` (the pixel each point falls
    in; outside the image: the nearest border pixel) of source ``k`` (or of source ``maps[k, i]``, ``maps # [K', n]``
    int64, for ``uv # [K', 2, n]``). ``# [K, n]``"""
    K, H, W = falloff.shape
    col = uv[:, 0].floor().clamp(0, W - 1).long()
    row = uv[:, 1].floor().clamp(0, H - 1).long()
    k = torch.arange(K, device=uv.device)[:, None] if maps is None else maps
    flat = (k * H + row) * W + col  # [K, n]
    return falloff.reshape(-1)[flat]


def apply_mask_factor(w: Tensor, factor: Tensor) -> Tensor:
    """Blend weights ``w # [n, K]`` times ``factor # [n, K]`` (:func:`mask_factor`), normalised again; rows whose
    weights all vanish keep ``w``. ``# [n, K]``"""
    u = w * factor.to(w)
    total = u.sum(1, keepdim=True)
    return torch.where(total > 0, u / total.clamp_min(1e-12), w)


def consensus_weights(rgb: Tensor, w: Tensor, sigma: float) -> Tensor:
    """Blend weights ``w # [n, K]`` re-weighted by how well each source's colour ``rgb # [n, K, 3]`` agrees with the
    blend: ``w_k exp(-|c_k - m|^2 / (2 sigma^2))``, ``m`` the blended colour, normalised again (a highlight or an
    occluder that one source sees is an outlier; rows whose weights all vanish keep ``w``); two rounds, the second
    around the first's blend (the first ``m`` is pulled toward the outlier). ``sigma <= 0``: ``w``. ``# [n, K]``"""
    if sigma <= 0:
        return w
    v = w
    for _ in range(2):
        m = (v[..., None] * rgb).sum(1, keepdim=True)  # [n, 1, 3]
        u = w * torch.exp(-((rgb - m) ** 2).sum(-1) / (2 * sigma * sigma))  # [n, K]
        total = u.sum(1, keepdim=True)
        v = torch.where(total > 1e-12, u / total.clamp_min(1e-12), w)
    return v


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
                             **kwargs)


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


def level_of_detail(mesh, budget: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``(vertices # [V, 3], faces # [F, 3])`` a renderer draws of ``mesh`` (a ``trimesh.Trimesh`` or such a pair):
    at most ``budget`` faces (quadric edge collapse, :func:`omnirecon.mesh.clean.decimate`), the mesh itself when it
    fits or ``budget`` is 0."""
    vertices, faces = (mesh.vertices, mesh.faces) if hasattr(mesh, "faces") else mesh
    if budget <= 0 or len(faces) <= budget:
        return vertices, faces
    import trimesh

    from omnirecon.mesh.clean import decimate

    small = decimate(trimesh.Trimesh(np.asarray(vertices), np.asarray(faces), process=False), budget)
    return np.asarray(small.vertices), np.asarray(small.faces)


class MeshRenderer:
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
            cams = sources.cameras.to(device=self.device, dtype=self.dtype)
            self._centers = cams.centers.T[:, :, None].contiguous()  # [3, K, 1]
            self._centers_t = cams.centers.contiguous()  # [K, 3]
            self._center_sq = (cams.centers * cams.centers).sum(1, keepdim=True)  # [K, 1]
            self._proj = (cams.K @ cams.w2c[:, :3, :]).reshape(-1, 4)  # [3K, 4]: world -> (u z, v z, z)
            self._size = torch.tensor([cams.width, cams.height], dtype=self.dtype, device=self.device)[None, :, None]
            self._two_over_size = 2 / self._size  # pixel coordinates -> grid_sample's [-1, 1]
            self._minus_one = torch.tensor(-1.0, dtype=self.dtype, device=self.device)
            self._images = sources.images.permute(0, 3, 1, 2)  # [K, 3, H, W]
            self._rgb = TexelAtlas(self._images, "border")
            self._one = torch.ones(1, 2, 1, dtype=self.dtype, device=self.device)  # taps at pixel coordinates
            if self.options.fused:
                self._feat, self._mlp = self._fold(model.appearance)
                self._uv_to_texel = self._feat._scale / self._size  # source pixels -> feature texels
        self._pool = ThreadPoolExecutor(self.options.workers) if self.options.workers > 1 and self.options.fused else None
        self._centres: dict[tuple[int, int], Tensor] = {}
        self._source_ids: Tensor | None = None  # a _subset's sources among the maps' (None: all, in order)
        self._parent: MeshRenderer | None = None  # a _subset's renderer over every source
        self.mask_falloff: Tensor | None = None
        """With the angle blend and ``options.source_masks``, sources that carry masks: :func:`mask_falloff`.
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

    def _fold(self, app) -> tuple[TexelAtlas, list[Tensor]]:
        """The appearance branch prepared for :meth:`_fused` (module docstring): the texel table of
        ``W F_i + b`` (border ``b``) and the MLP: ``W1`` split into its feature and direction columns
        and transposed (``[C, h1]``, ``[3, h1]``), ``b1 # [h1]``, then ``W2``, ``b2``, ``W3``, ``b3`` as
        ``[out, in]`` matrices and ``[out, 1]`` biases."""
        dt = self.dtype
        W, b = app.proj.weight.to(dt), app.proj.bias.to(dt)  # [C, C], [C]
        maps = torch.einsum("dc,kchw->kdhw", W, self.features.maps) + b[:, None, None]  # [K, C, h, w]
        (w1, b1), (w2, b2), (w3, b3) = [(m.weight.to(dt), m.bias.to(dt)[:, None]) for m in app.mlp
                                        if isinstance(m, torch.nn.Linear)]
        C = W.shape[0]
        # layer 1 row-major ([K n, C] @ [C, h1]), the narrower layers 2 and 3 column-major
        mlp = [t.contiguous() for t in (w1[:, :C].T, w1[:, C:].T, b1[:, 0], w2, b2, w3, b3)]
        return TexelAtlas(maps, "zeros", pad_value=b), mlp

    def source_depths(self) -> Tensor:
        """Rasterized z-depth of the mesh at every source camera, 0 = background (the depth pass). ``# [K, H, W]``"""
        cams = self.sources.cameras
        return torch.stack([self.rasterizer.depth(cams[i]).clone() for i in range(len(cams))])

    # ------------------------------------------------------------------ per point
    def project(self, points: Tensor, layer: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Project ``points # [3, n]`` (channel-first) into every source: pixel coordinates
        ``uv # [K, 2, n]``, camera z-depth ``z # [K, n]`` and ``mask # [K, n]`` (in front, inside the
        image and, with the visibility test on, not occluded; points where ``layer # [n]`` bool is True, the fill's
        background layer, skip the occlusion test, as ``finetune`` scores them)."""
        uv, z, mask = self._frame_points(points)
        if self.source_depth_max is not None:
            vis = self.visible(uv, z)
            mask &= vis if layer is None else vis | layer  # the fill's far layer: every source that frames it
        return uv, z, mask

    def _frame_points(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """:meth:`project` without the occlusion test: ``uv # [K, 2, n]``, ``z # [K, n]`` and in front and inside the
        image ``# [K, n]``."""
        K = self.num_views
        uvz = torch.addmm(self._proj[:, 3:], self._proj[:, :3], points).reshape(K, 3, -1)  # [K, 3, n]
        z = uvz[:, 2]
        uv = uvz[:, :2] / z.clamp_min(1e-6)[:, None]  # as Cameras.project
        inside = (uv >= 0) & (uv < self._size)  # [K, 2, n]
        return uv, z, (z > 1e-6) & inside[:, 0] & inside[:, 1]  # (faster than .all(1) over the size-2 axis)

    def visible(self, uv: Tensor, z: Tensor) -> Tensor:
        """Occlusion test (module docstring) of points at source pixel coordinates ``uv # [K, 2, n]``
        with source z-depths ``z # [K, n]``. ``# [K, n]`` bool"""
        if self.source_depth_max is None:
            raise ValueError("the occlusion test needs MeshRenderOptions(visibility=True)")
        return unoccluded(self.source_depth_max, uv, z, self.options.visibility_tol, self._all_ids(uv.shape[2]))

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
            uv, _, mask = self.project(points.T, layer)
            if self.options.blend == "angle":
                omega = angle_weights(points, origin, self.sources.cameras.centers.to(points), mask.T,
                                      self.options.angle_sources or self.num_views)  # [P, K]
                if self.mask_falloff is not None:
                    omega = apply_mask_factor(omega, self._mask_factor(uv, on_mesh).T)
                omega = omega.T  # [K, P]
                if self.options.consensus > 0:
                    colours = self._rgb.sample(*self._rgb.taps(uv / self._size)).reshape(self.num_views, -1, 3)
                    omega = consensus_weights(colours.transpose(0, 1), omega.T, self.options.consensus).T
                shaded = ShadeResult(surf, omega, mask, uv / self._size, None, covered)
                return replace(shaded, rgb=self.blend(shaded, self._rgb)) if with_rgb else shaded
            out = self.model.shade(self.features, points, origin.expand_as(points),
                                   visible=mask.T if self.options.visibility else None)
            return ShadeResult(surf, out["blend"].T, mask, uv / self._size, out["rgb"] if with_rgb else None, covered)

    def _shade_points(self, p: Tensor, d_t: Tensor, with_rgb: bool, with_coords: bool = False,
                      layer: Tensor | None = None, on_mesh: Tensor | None = None,
                      with_mask: bool = True) -> tuple[Tensor | None, Tensor | None, Tensor | None, Tensor | None]:
        """``OmniRecon.shade``, fused (module docstring), at points ``p # [3, n]`` (channel-first) seen along
        ``d_t # [3, n]`` (target -> point, any positive length): blend weights ``omega # [K, n]``, the
        mask ``# [K, n]``, with ``with_coords`` the source image fractions ``# [K, 2, n]`` and, with
        ``with_rgb``, the blended source colour ``# [3, n]``. ``layer # [n]`` bool: points on the fill's far layer (no
        occlusion test); ``on_mesh # [n]`` bool: points on the mesh (the only ones the source masks weigh; ``None``:
        all). Without ``with_mask`` (and with the angle blend, no ``with_coords`` nor consensus), only the colour:
        ``(None, None, None, rgb)``."""
        K = self.num_views
        angle = self.options.blend == "angle"
        if angle and not (with_mask or with_coords or self.options.consensus > 0):  # the frame path
            uv, z, framed = self._frame_points(p)
            top = self._angle_top(p, d_t, uv, z, framed, False, layer, on_mesh)
            wide = top[2]
            if self._parent is None or not len(wide) or not with_rgb:
                return None, None, None, self._sparse_rgb(*top, uv) if with_rgb else None
            rgb = self._sparse_rgb(*top[:2], wide[:0], top[3][:, :0], uv)  # points no candidate weighs: every source
            rgb[:, wide] = self._parent._shade_points(p[:, wide], d_t[:, wide], True, layer=_pick(layer, wide),
                                                      on_mesh=_pick(on_mesh, wide), with_mask=False)[3]
            return None, None, None, rgb
        uv, z, mask = self.project(p, layer)  # [K, 2, n], [K, n]
        st = uv / self._size if with_coords else None  # [K, 2, n] image fractions
        seen = mask.sum(0)  # [n] sources that see each point
        few = seen < 2
        n_few = int(few.sum())
        top = None
        if angle:
            top = self._angle_top(p, d_t, uv, z, mask, True, layer, on_mesh)
            om = self._dense(*top)
        elif n_few == 0:
            om = self._blend_logits(p, d_t, uv, mask)
        else:  # omega needs no network where fewer than 2 sources see the point (module docstring)
            om = torch.where(seen == 0, 1.0 / K, mask.to(self.dtype))  # [K, n]
            if n_few < p.shape[1]:
                if n_few * self.SKIP_BELOW < p.shape[1]:  # few such points: not worth the compaction
                    om = torch.where(few, om, self._blend_logits(p, d_t, uv, mask))
                else:
                    i = (~few).nonzero()[:, 0]
                    om[:, i] = self._blend_logits(p[:, i], d_t[:, i], uv[:, :, i], mask[:, i])
        rgb = None
        consensus = self.options.blend == "angle" and self.options.consensus > 0
        if with_rgb and top is not None and not consensus:
            return om, mask, st, self._sparse_rgb(*top, uv)
        if with_rgb or consensus:  # the model's own sampling of the source colours
            grid = torch.addcmul(self._minus_one, uv, self._two_over_size).transpose(1, 2)[:, None]  # [K, 1, n, 2]
            c = F.grid_sample(self._images, grid, align_corners=False, padding_mode="border")[:, :, 0]  # [K, 3, n]
            if consensus:
                om = consensus_weights(c.permute(2, 0, 1), om.T, self.options.consensus).T.contiguous()
        if with_rgb:
            rgb = c[0].mul_(om[0])  # [3, n]
            for k in range(1, K):
                rgb.addcmul_(c[k], om[k])
        return om, mask, st, rgb

    def _sparse_rgb(self, w: Tensor, idx: Tensor, wide: Tensor, wide_om: Tensor, uv: Tensor) -> Tensor:
        """The angle blend's colour ``# [3, n]`` from :meth:`_angle_top`, sampling only the weighted sources: one
        :class:`TexelAtlas` tap set per (point, source) pair of ``idx``, summed with the weights by ``embedding_bag``
        (bilinear, border padding: ``grid_sample``'s colours up to the float rounding of the coordinates); the ``wide``
        points blend every source as :meth:`_shade_points` does."""
        k1, n = idx.shape
        sel = uv.gather(0, idx[:, None].expand(k1, 2, n))  # [k1, 2, n] source pixels
        index, weight = self._rgb.taps(sel, scale=self._one, maps=self._ids(idx))  # [k1 n, 4]
        weight = weight.reshape(k1, n, 4).mul_(w[..., None]).transpose(0, 1).reshape(n, 4 * k1)
        rgb = F.embedding_bag(index.reshape(k1, n, 4).transpose(0, 1).reshape(n, 4 * k1), self._rgb.rows,
                              per_sample_weights=weight, mode="sum").T  # [3, n]
        if len(wide):
            grid = torch.addcmul(self._minus_one, uv[:, :, wide], self._two_over_size).transpose(1, 2)[:, None]
            images = self._images if self._source_ids is None else self._images[self._source_ids]
            c = F.grid_sample(images, grid, align_corners=False, padding_mode="border")[:, :, 0]  # [K, 3, m]
            rgb[:, wide] = (c * wide_om[:, None]).sum(0)
        return rgb.contiguous()

    SKIP_BELOW = 8
    """:meth:`_shade_points` compacts the points at least two sources see when the others are at least
    ``1 / SKIP_BELOW`` of a chunk (below that, the gather costs more than the network it saves)."""

    def _mask_factor(self, uv: Tensor, on_mesh: Tensor | None) -> Tensor:
        """:func:`mask_factor` at source pixels ``uv # [K, 2, n]``, 1 at the points not on the mesh (``on_mesh # [n]``
        bool False: the fill's points, off the object where the target sees no surface). ``# [K, n]``"""
        fac = mask_factor(self.mask_falloff, uv, self._all_ids(uv.shape[2]))
        return fac if on_mesh is None else torch.where(on_mesh, fac, torch.ones_like(fac))

    def _angle_top(self, p: Tensor, d_t: Tensor, uv: Tensor, z: Tensor, seen: Tensor, tested: bool,
                   layer: Tensor | None = None, on_mesh: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``blend="angle"``: :func:`lumigraph_weights` at points ``p # [3, n]`` seen along ``d_t # [3, n]`` by the
        sources of ``seen # [K, n]`` (times :meth:`_mask_factor` at their pixels ``uv # [K, 2, n]`` when the sources
        carry masks; ``on_mesh # [n]``: which points lie on the mesh), for the ``k + 1`` sources nearest by angle only
        (``k`` = ``angle_sources``; the largest cosines, no arccos of the others). Unless ``tested``, ``seen`` is
        :meth:`_frame_points`' (no occlusion test) and the occlusion test (source z-depths ``z # [K, n]``; ``layer``
        as :meth:`project`) runs on the ``2 (k + 1)`` nearest only, and on every source for the points where fewer
        than ``k + 1`` of those pass and more sources frame them (the same sources as testing every one).

        Returns weights ``w # [k1, n]`` of sources ``idx # [k1, n]`` (``k1 = min(k + 1, K)``; the last weighs 0
        unless ``k1 = K``), the points no source weighs ``wide # [m]`` (every source at ``1 / K``, times the mask
        factor) and their weights ``# [K, m]``."""
        K, n = seen.shape
        k = max(1, min(self.options.angle_sources or K, K))
        k1 = min(k + 1, K)
        t = d_t / _norm(d_t)  # [3, n] unit target rays
        cos = self._cosines(p, t).masked_fill_(~seen, -2.0)  # sources that do not see the point: after every one that does
        if tested or self.source_depth_max is None:
            c, idx = cos.topk(k1, dim=0)  # [k1, n]: ascending angle
        else:
            m = min(2 * k1, K)
            c, idx = cos.topk(m, dim=0)  # [m, n] the candidates
            vis = unoccluded(self.source_depth_max, uv.gather(0, idx[:, None].expand(m, 2, n)), z.gather(0, idx),
                             self.options.visibility_tol, self._ids(idx))
            c = c.masked_fill(~(vis if layer is None else vis | layer), -2.0)
            c, j = c.topk(k1, dim=0)  # sorted again: the occluded ones last
            idx = idx.gather(0, j)
            short = ((c[-1] < -1.5) & (seen.sum(0) > m)).nonzero()[:, 0]  # visible sources may lie beyond
            if len(short):
                vis = self.visible(uv[:, :, short], z[:, short])
                c[:, short], idx[:, short] = cos[:, short].masked_fill(
                    ~(vis if layer is None else vis | layer[short]), -2.0).topk(k1, dim=0)
        d_s = p[:, None] - self._centers[:, :, 0].T.gather(0, idx.reshape(-1, 1).expand(-1, 3)).T.reshape(3, k1, n)
        exact = (t[:, None] * (d_s / _norm(d_s))).sum(0).clamp_(-1, 1)  # [k1, n] the chosen sources' cosines
        ang = torch.arccos(exact).masked_fill_(c < -1.5, float("inf"))  # [k1, n]
        thresh = ang[k:k + 1] if K > k else torch.full_like(ang[:1], float("inf"))  # [1, n]
        w = (1 - ang / thresh).clamp_min(0) / ang.clamp_min(1e-3)  # inf angles -> 0 (or NaN, zeroed below)
        w = torch.where((ang <= ang[k - 1:k]) & torch.isfinite(w), w, torch.zeros_like(w))
        total = w.sum(0, keepdim=True)  # [1, n]
        w = w / total.clamp_min(1e-12)
        if self.mask_falloff is not None:
            fac = mask_factor(self.mask_falloff, uv.gather(0, idx[:, None].expand(k1, 2, n)), self._ids(idx))  # [k1, n]
            if on_mesh is not None:
                fac = torch.where(on_mesh, fac, torch.ones_like(fac))
            u = w * fac
            t2 = u.sum(0, keepdim=True)
            w = torch.where(t2 > 0, u / t2.clamp_min(1e-12), w)
        wide = (total[0] <= 0).nonzero()[:, 0]  # [m]
        wide_om = torch.full((K, len(wide)), 1.0 / K, dtype=w.dtype, device=w.device)
        if len(wide) and self.mask_falloff is not None:
            fac = self._mask_factor(uv[:, :, wide], None if on_mesh is None else on_mesh[wide])
            wide_om = apply_mask_factor(wide_om.T, fac.T).T
        return w, idx, wide, wide_om

    def _cosines(self, p: Tensor, t: Tensor) -> Tensor:
        """Cosine of the angle between each source's ray to points ``p # [3, n]`` and the unit target rays ``t # [3, n]``,
        ``t . (p - c) / |p - c|``, from two ``[K, 3] x [3, n]`` products (no ``[3, K, n]`` temporaries; the weights take
        the cosines of the chosen sources computed directly). ``# [K, n]``"""
        sq = torch.addmm(self._center_sq, self._centers_t, p, alpha=-2).add_((p * p).sum(0))  # [K, n] |p - c|^2
        return torch.addmm((t * p).sum(0)[None], self._centers_t, t, alpha=-1).mul_(sq.clamp_min_(1e-24).rsqrt_())

    def _frame_sources(self, depth: Tensor, size: tuple[int, int], origin: Tensor, rays, far_z):
        """``shader(sl)``: the renderer the frame's pixels ``sl`` (a slice of the row-major ``H W``) are shaded by
        (``options.frame_grid``): one over their candidate sources only (those the grid points within ``frame_grid``
        rows of theirs rank), or ``self`` (option off, not the angle blend, or more than half the sources candidates:
        lund's street, 25 sources, ran 360 -> 479 CPU-ms per frame with every subset).
        ``depth # [H W]`` (after the nearest fill; <= 0: none) of a frame of ``size = (H, W)`` seen from
        ``origin # [3]``; ``rays(pixels) # [3, g]``: the rays through pixels at camera z = 1; ``far_z(rays) # [g]``:
        the fill's far-layer depth (``None``: the background colour, no point)."""
        K, g = self.num_views, self.options.frame_grid
        k1 = min(max(1, self.options.angle_sources or K) + 1, K)
        H, W = size
        if self.options.blend != "angle" or g <= 0 or K <= 2 * k1:
            return lambda sl: self
        rows, cols = torch.arange(g // 2, H, g), torch.arange(g // 2, W, g)
        pix = (rows[:, None] * W + cols[None]).reshape(-1).to(self.device)  # [G] grid pixels
        z, d = depth[pix], rays(pix)  # [G], [3, G]
        if far_z is None:
            pix, z, d = pix[z > 0], z[z > 0], d[:, z > 0]
        else:
            z = torch.where(z > 0, z, far_z(d))
        p = d * z + origin[:, None]  # [3, G]
        framed = self._frame_points(p)[2]
        c, idx = self._cosines(p, d / _norm(d)).masked_fill_(~framed, -2.0).topk(min(2 * k1, K), dim=0)  # [2 k1, G]
        idx = idx.masked_fill_(c < -1.5, K)  # K: none

        def shader(sl: slice) -> MeshRenderer:
            near = (pix >= (sl.start // W - g) * W) & (pix < ((sl.stop - 1) // W + g + 1) * W)  # [G]
            cand = idx[:, near].unique()  # sorted source indices (K last)
            cand = cand[cand < K]
            return self if len(cand) == 0 or 2 * len(cand) > K else self._subset(cand)  # worth it below half

        return shader

    def _subset(self, cand: Tensor) -> MeshRenderer:
        """A shallow copy of this renderer over sources ``cand # [M]``: its per-source geometry indexed, its maps (colour
        atlas, occlusion depths, mask falloff) shared and read through :meth:`_ids`."""
        import copy

        sub = copy.copy(self)
        sub.num_views, sub._source_ids, sub._parent = len(cand), cand, self
        sub._centers, sub._centers_t = self._centers[:, cand].contiguous(), self._centers_t[cand].contiguous()
        sub._center_sq = self._center_sq[cand].contiguous()
        sub._proj = self._proj.reshape(-1, 3, 4)[cand].reshape(-1, 4).contiguous()  # [3M, 4]
        return sub

    def _ids(self, idx: Tensor) -> Tensor:
        """Source indices ``idx # [k, n]`` of this renderer as indices of its maps (a :meth:`_subset`'s differ)."""
        return idx if self._source_ids is None else self._source_ids[idx]

    def _all_ids(self, n: int) -> Tensor | None:
        """Every source's map index for ``n`` points (``None``: the identity). ``# [K, n]``"""
        return None if self._source_ids is None else self._source_ids[:, None].expand(-1, n)

    def _dense(self, w: Tensor, idx: Tensor, wide: Tensor, wide_om: Tensor) -> Tensor:
        """:meth:`_angle_top`'s weights over every source. ``# [K, n]``"""
        om = torch.zeros(self.num_views, w.shape[1], dtype=w.dtype, device=w.device).scatter_(0, idx, w)
        if len(wide):
            om[:, wide] = wide_om
        return om

    def _blend_logits(self, p: Tensor, d_t: Tensor, uv: Tensor, mask: Tensor) -> Tensor:
        """The appearance network's blend weights ``omega # [K, n]`` at points ``p # [3, n]`` seen along
        ``d_t # [3, n]``, projecting to source pixels ``uv # [K, 2, n]`` with ``mask # [K, n]``."""
        w1z, w1d, b1, w2, b2, w3, b3 = self._mlp
        K, n = self.num_views, p.shape[1]
        z = self._feat.sample(*self._feat.taps(uv, mask, self._uv_to_texel)).relu_()  # [K n, C]: ReLU(W f + b)
        d_s = p[:, None] - self._centers  # [3, K, n] sources -> point
        rel = (d_t / _norm(d_t))[:, None] - d_s / _norm(d_s)  # [3, K, n]
        hid = torch.addmm(b1, z, w1z).addmm_(rel.reshape(3, K * n).T, w1d).relu_()  # [K n, h1]
        hid = torch.addmm(b2, w2, hid.T).relu_()  # [h2, K n]
        logit = torch.addmm(b3, w3, hid).reshape(K, n).masked_fill_(~mask, -1e9)
        return torch.softmax(logit, dim=0)  # [K, n]

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
        the points on the fill's far layer, on the mesh (:meth:`_shade_points`)."""
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

    # ------------------------------------------------------------------ images
    def blend(self, shaded: ShadeResult, signal: Tensor | TexelAtlas) -> Tensor:
        """Blend a per-view ``signal # [K, C, H', W']`` (channel-first, or a border-padded
        :class:`TexelAtlas`) at ``shaded``'s points with its weights (bilinear, border padding). ``# [P, C]``"""
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
        if self._shared is None:
            self.rasterizer.close()

    def __enter__(self) -> MeshRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class ViewCache:
    """The work per source view of one mesh path over one scene's views, shared by the renderers (:class:`MeshRenderer`) of
    frames that blend different sets of them (a video whose every frame blends its nearest sources, as ``finetune
    --nearest`` scores): one rasterizer (one GL context, the mesh uploaded once), each view's occlusion depths
    (:func:`block_depth_max` of its rasterized depth) and :func:`mask_falloff` computed once, and each set of views
    encoded once (appearance maps only).

    A view's encoding is cached per *set*, not per view: Omni-Recon's encoder normalises with the batch statistics of
    the views it encodes together (BatchNorm without running averages, :mod:`omnirecon.models.omnirecon`), so a view's
    features depend on its companions. Every :meth:`renderer` therefore renders exactly what a :class:`MeshRenderer`
    built for its views alone renders (tested bit for bit). Use as a context manager (:meth:`close` frees the
    rasterizer).

    Args:
        model, mesh, options: as :class:`MeshRenderer`.
        scene: The :class:`~omnirecon.data.scene.Scene` whose views the renderers take as sources
            (:meth:`Sources.from_scene`); the mesh is in its frame.
    """

    def __init__(self, model, mesh, scene, options: MeshRenderOptions | None = None):
        self.model, self.scene = model, scene
        self.options = options or MeshRenderOptions()
        vertices, faces = level_of_detail(mesh, self.options.face_budget)
        self.rasterizer = MeshRasterizer(vertices, faces, backend=self.options.backend,
                                         cull_back_faces=self.options.cull_back_faces)
        """The one rasterizer of every renderer."""
        self._views: dict[str, dict[int, Tensor]] = {}
        self._features: dict[tuple[int, ...], object] = {}

    def renderer(self, views: list[int]) -> MeshRenderer:
        """A :class:`MeshRenderer` over the scene views ``views`` (in this order) that shares this cache."""
        views = [int(v) for v in views]
        return MeshRenderer(self.model, None, Sources.from_scene(self.scene, views), self.options, shared=(self, views))

    def features(self, views: list[int], encode):
        """``encode(sources)`` of ``views``, computed on the first call for this set (class docstring)."""
        key = tuple(views)
        if key not in self._features:
            self._features[key] = encode(Sources.from_scene(self.scene, views))
        return self._features[key]

    def per_view(self, kind: str, views: list[int], make) -> Tensor:
        """Per-view maps ``kind`` of ``views`` stacked on a first axis; ``make(k) # [1, ...]`` computes the map of
        the ``k``-th of ``views`` on its first request."""
        cache = self._views.setdefault(kind, {})
        for k, v in enumerate(views):
            if v not in cache:
                cache[v] = make(k)
        return torch.cat([cache[v] for v in views])

    def close(self) -> None:
        """Free the rasterizer's GL context."""
        self.rasterizer.close()

    def __enter__(self) -> ViewCache:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def render_signal(model, mesh, sources: Sources, camera: Cameras, signal: Tensor, background: float | Tensor = 0.0,
                  options: MeshRenderOptions | None = None) -> Tensor:
    """Blend a per-view ``signal # [K, H', W', C]`` (one map per source) at ``camera``'s surface points
    with the appearance branch's weights, ``background`` where no triangle. ``# [H, W, C]``

    One-shot :meth:`MeshRenderer.render_signal` (encodes the sources, builds and frees a renderer); keep
    a :class:`MeshRenderer` for many frames or signals instead.
    """
    with MeshRenderer(model, mesh, sources, options) as renderer:
        return renderer.render_signal(camera, signal, background)["signal"]


def render_frames(renderer: MeshRenderer, cameras: Cameras, warmup: bool = True) -> tuple[list[np.ndarray], list[float]]:
    """Render every camera of ``cameras`` with ``renderer`` (with ``warmup``, one untimed warm-up frame first): 8-bit
    frames ``# [H, W, 3]`` and the wall seconds of each render."""
    if warmup:
        renderer.render(cameras[0].to(dtype=torch.float32), extras=False)
    images, seconds = [], []
    for i in range(len(cameras)):
        start = time.perf_counter()
        rgb = renderer.render(cameras[i].to(dtype=torch.float32), extras=False)["rgb"]
        seconds.append(time.perf_counter() - start)
        images.append((rgb.float().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8))
    return images, seconds
