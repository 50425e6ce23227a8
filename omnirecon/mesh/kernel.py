"""The mesh path's blend, one implementation: pure functions on tensors from surface points to weights and colour.

A point seen from a target camera blends ``K`` source views (``shared/docs/omnirecon.md`` §7):

1. **Visible sources.** A source sees the point when it lies in front of it and inside its image and, with the
   occlusion test (not in the paper), is not hidden: :func:`block_depth_max` of each source's rasterized z-depth,
   computed once per scene, and :func:`unoccluded`. The point's z-depth in source ``i`` may exceed the largest of the
   four rasterized depths around its projection (the bilinear footprint; background and outside the image count as
   infinitely far) by at most ``(1 + tol)``. Taking the largest of the four makes the test one-sided and safe on the
   point's own surface: on a plane covering the four pixel centres z is convex in the image, so the largest corner
   depth is at least the point's own depth; being one-sided, it also keeps points seen just past an occluder's
   silhouette. Masked sources are treated exactly like sources the point projects outside of
   (``OmniRecon.shade``'s ``visible`` argument): a point no source sees blends all sources uniformly, as the
   volumetric path does. Points on the fill's far layer skip the test.
2. **Weights.** ``"network"``: the appearance branch (``OmniRecon.shade``; the real-time renderer's fused twin in
   :mod:`omnirecon.mesh.shader`, equal to float tolerance). ``"angle"``: :func:`angle_weights`, the unstructured
   lumigraph's blend by viewing angle alone over the ``k`` nearest visible sources (:func:`lumigraph`), times each
   source's :func:`mask_falloff` where the sources carry object masks that hold the scene
   (:func:`apply_mask_factor`), optionally re-weighted by colour agreement (:func:`consensus_weights`).
3. **Colour.** :func:`blend_colours`: the weighted sum of the sources' colours at the point's projections (bilinear,
   border padding).

Fill and cracks (the points of pixels the mesh misses) are :mod:`omnirecon.mesh.fill`'s; the blur at depth edges is
:func:`omnirecon.render.edges.soften_edges`. The real-time renderer (:class:`omnirecon.mesh.ibr.MeshRenderer`, through
:mod:`omnirecon.mesh.shader`) and ``finetune``'s scores and tuning steps (:mod:`omnirecon.mesh.pixels`, with gradients)
call these functions; ``tests/mesh/test_kernel.py`` checks that each is defined here only and that both paths give
the same colours.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor


def norm3(d: Tensor) -> Tensor:
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
    w = lumigraph(ang, near[:, k - 1:k], thresh)
    total = w.sum(1, keepdim=True)
    return torch.where(total > 0, w / total.clamp_min(1e-12), torch.full_like(w, 1.0 / K))


def lumigraph(ang: Tensor, kth: Tensor, thresh: Tensor) -> Tensor:
    """The unstructured lumigraph's weight of sources at angles ``ang`` (radians, ``inf``: not seen) before
    normalising: ``(1 - a / a_(k+1)) / a`` for the ``k`` nearest (``a <= kth``, the ``k``-th smallest angle), 0 for the
    rest and for unseen sources; ``thresh`` is ``a_(k+1)`` (``inf`` when there are only ``k`` sources). ``kth`` and
    ``thresh`` broadcast against ``ang`` (any layout: :func:`lumigraph_weights` ``# [P, K]`` against ``# [P, 1]``,
    the fused shader's nearest ``# [k + 1, n]`` against ``# [1, n]``). ``# like ang``"""
    w = (1 - ang / thresh).clamp_min(0) / ang.clamp_min(1e-3)  # inf angles -> 0 (or NaN, zeroed here)
    return torch.where((ang <= kth) & torch.isfinite(w), w, torch.zeros_like(w))


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


def apply_mask_factor(w: Tensor, factor: Tensor, dim: int = 1) -> Tensor:
    """Blend weights ``w # [n, K]`` times ``factor # [n, K]`` (:func:`mask_factor`), normalised again over the sources
    (axis ``dim``: 0 for the fused shader's ``# [K, n]``); points whose weights all vanish keep ``w``. ``# like w``"""
    u = w * factor.to(w)
    total = u.sum(dim, keepdim=True)
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


def angle_blend_weights(points: Tensor, origin: Tensor, centers: Tensor, seen: Tensor, k: int,
                        factor: Tensor | None = None) -> Tensor:
    """The angle blend's weights of points ``# [P, 3]`` seen from ``origin # [3]``: :func:`angle_weights` over the
    sources ``seen # [P, K]`` bool (centres ``# [K, 3]``), times the sources' mask ``factor # [P, K]``
    (:func:`mask_factor`; 1 for points off the mesh; ``None``: no masks), normalised again. What
    ``MeshRenderer(fused=False)`` blends and what ``finetune`` scores and tunes with (``omnirecon.mesh.pixels``);
    the fused shader computes the same over each point's nearest sources only. ``# [P, K]``"""
    w = angle_weights(points, origin, centers, seen, k)
    return w if factor is None else apply_mask_factor(w, factor)


def blend_colours(rgb: Tensor, w: Tensor, consensus: float = 0.0) -> Tensor:
    """The blended colour of each point from its sources' colours ``rgb # [n, K, 3]`` and weights ``w # [n, K]``
    (re-weighted by :func:`consensus_weights` of width ``consensus``; 0: as given). Differentiable. ``# [n, 3]``"""
    w = consensus_weights(rgb, w.to(rgb), consensus)
    return (w[:, :, None] * rgb).sum(1)
