"""The mesh path's fill: a background layer for pixels no triangle covers (``MeshRenderOptions.fill``).

A pixel the mesh misses is given the point where its ray leaves the scene's bounds box (the box's far
side), never farther than the sources' far z-depth; the mesh renderer then shades it with the same
image-based blend as the surface, so no pixel is left at a background colour.

**Nearest fill** (``MeshRenderOptions.fill="nearest"``, ``finetune --fill nearest``): a missed pixel within
:data:`NEAREST_FILL_REACH` of a pixel the mesh covers takes that pixel's rendered z-depth (:func:`nearest_depth`; never
a photo), the others keep the background layer: an object whose mesh stops short of its silhouette is continued
at its own depth instead of showing the far layer there.

**Cracks** (``MeshRenderOptions.cracks``, ``finetune --cracks``), whatever the fill: a missed pixel the mesh encloses
(:func:`crack_pixels`: inside the morphological closing of the covered pixels) takes the nearest covered pixel's
z-depth too. Pinholes and the seams between completion's per-pixel fills, seen from between the training views, are
surface the mesh lost, not background: the far layer or the background colour there was the white speckle of the
procedural scenes' renders.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.render.raster import Surface


def layer_box(rig: str, bounds: Tensor | None) -> Tensor | None:
    """The box whose far side carries the background layer: ``bounds``, except on object rigs (``None``: the layer
    at the sources' far z-depth). An object capture's bounds hug the object, so a layer on the box's far side sits
    just behind it, and sources tens of degrees away see the object there: on DTU it painted streaks of the object
    beside it. At the far z-depth the nearest sources see what lies past the object: on dtu_scan24 and dtu_scan37
    the held-out whole image rose and the masks stayed about the same (``python -m bench dtu_split``)."""
    return None if rig == "object" else bounds


def ray_basis(camera: Cameras) -> tuple[Tensor, Tensor]:
    """``A # [3, 3]`` with the ray direction at camera z = 1 through pixel ``(u, v)`` equal to
    ``u A[0] + v A[1] + A[2]`` (``R ((u - cx) / fx, (v - cy) / fy, 1)``, as :meth:`Cameras.rays`), and the
    camera centre ``# [3]``, float32, of one camera."""
    R = camera.R[0].float()  # [3, 3] camera -> world rotation
    fx, fy, cx, cy = (float(x[0]) for x in (camera.fx, camera.fy, camera.cx, camera.cy))
    A = torch.stack([R[:, 0] / fx, R[:, 1] / fy, R[:, 2] - R[:, 0] * (cx / fx) - R[:, 1] * (cy / fy)])  # [3, 3]
    return A, camera.centers[0].float()


def exit_depth(d: Tensor, origin: Tensor, far: float, bounds: Tensor | None = None) -> Tensor:
    """z-depth where rays ``origin + z d`` (``d # [3, M]`` channel-first, camera z = 1) leave the box
    ``bounds # [2, 3]`` (its far side), at most ``far`` (rays that miss the box, or no box: ``far``). ``# [M]``"""
    z = torch.full((d.shape[1],), float(far), dtype=d.dtype, device=d.device)
    if bounds is None:
        return z
    b = (bounds.to(d) - origin.to(d))[:, :, None]  # [2, 3, 1] box corners relative to the origin
    inv = d.abs().clamp_min(1e-12).copysign(d).reciprocal()  # [3, M]
    t1, t2 = inv * b[0], inv * b[1]  # [3, M]
    t_in, t_out = torch.minimum(t1, t2).amax(0), torch.maximum(t1, t2).amin(0)  # [M]
    hit = (t_out > t_in.clamp_min(0)) & (t_out > 0)
    return torch.where(hit, torch.minimum(t_out, z), z)


def fill_points(camera: Cameras, pixels: Tensor, far: float, bounds: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The background layer at flat pixel indices ``pixels # [M]`` of one camera: where each pixel-centre
    ray leaves the box ``bounds # [2, 3]`` (its far side), at most at z-depth ``far`` (rays that miss the
    box, or no box: at ``far``). Returns world ``points # [M, 3]`` and their z-depths ``# [M]`` (float32).

    Per frame this runs on every pixel the mesh misses (up to the whole image), so it is written for
    speed: the ray direction with camera z = 1 is affine in the pixel centre ``(u, v)``
    (:func:`ray_basis`), one ``[M, 2] @ [2, 3]`` product, and the slab test (:func:`exit_depth`)
    multiplies by its reciprocal, in float32."""
    pixels = pixels.to(camera.device)
    A, o = ray_basis(camera)
    uv = torch.stack([pixels % camera.width, pixels // camera.width], -1).float() + 0.5  # [M, 2] pixel centres
    d = torch.addmm(A[2], uv, A[:2])  # [M, 3]: origin + z * d is at z-depth z
    z = exit_depth(d.T, o, far, bounds)
    return torch.addcmul(o, z[:, None], d), z


def with_fill(surface: Surface, camera: Cameras, far: float, bounds: Tensor | None = None) -> tuple[Surface, int]:
    """``surface`` plus the background layer (:func:`fill_points`) at every pixel it does not cover; the
    first returned count of pixels are the real surface's."""
    miss = torch.ones(surface.height * surface.width, dtype=torch.bool)
    miss[surface.pixels] = False
    miss = miss.nonzero()[:, 0]
    if not len(miss):
        return surface, len(surface.pixels)
    points, depth = fill_points(camera, miss, far, bounds)
    return replace(surface, pixels=torch.cat([surface.pixels, miss]), points=torch.cat([surface.points, points]),
                   depth=torch.cat([surface.depth, depth])), len(surface.pixels)


NEAREST_FILL_REACH = 0.15
"""The nearest fill moves the missed pixels within this fraction of the image's long side of a covered pixel (the
rest keep the far layer). On dtu_scan37 (angle blend, nearest 4) the held-out mask score is the same from a few
pixels' reach on, and the whole image rises with the reach up to this one; every pixel scored lower (far background,
e.g. the dark table, is better on the far layer)."""


CRACK_RADIUS = 2
"""Cracks (:func:`crack_pixels`) are closed with a ``(2 r + 1)``-pixel square: gaps up to about ``2 r`` pixels wide
that the mesh encloses. On the held-out mesh path before tuning (``finetune --nearest 6``, the procedural scenes'
background colour where nothing is covered, their ``stereo+model`` meshes) r = 2 scored best of 0-3 on a procedural
scene and raised the demo scene."""


def crack_pixels(covered: np.ndarray, radius: int = CRACK_RADIUS) -> np.ndarray:
    """Pixels outside ``covered # [H, W]`` bool inside its morphological closing by a ``(2 radius + 1)``-pixel square:
    gaps the covered pixels enclose. A pixel beside an outline, with a window of that size clear of every covered
    pixel, is not one; the image is padded by its edge pixels, so what runs off the border is no crack either.
    ``# [H, W]`` bool"""
    import cv2

    if radius <= 0 or covered.all() or not covered.any():
        return np.zeros_like(covered, dtype=bool)
    padded = np.pad(covered, radius, mode="edge").view(np.uint8)
    square = np.ones((2 * radius + 1,) * 2, np.uint8)  # the closing by a square: its dilation, then its erosion
    closed = cv2.erode(cv2.dilate(padded, square), square)  # (the pad absorbs any border effect: cropped below)
    return closed[radius:-radius, radius:-radius].astype(bool) & ~covered


def nearest_depth(depth: np.ndarray, reach: float = NEAREST_FILL_REACH, cracks: int = 0) -> np.ndarray:
    """``depth # [H, W]`` (z-depth, 0 = no surface) with every empty pixel within ``reach`` times the long side of a
    covered pixel, and every crack (:func:`crack_pixels` of radius ``cracks``), given the z-depth of the nearest
    covered pixel (Euclidean distance; ties below); the others stay 0. ``# [H, W]``

    With cracks alone (``reach`` below a pixel), a covered pixel lies within ``cracks`` pixels along each axis of a
    crack (the closing's dilation found one there), so only the offsets up to ``cracks * sqrt(2)`` px are searched,
    nearest first, at the cracks only (:func:`_nearest_within`); otherwise one Euclidean distance transform of the
    image. Of covered pixels at the same distance, both take the one in the smaller column, then the smaller row (as
    scipy's transform does, and the web viewer's fill)."""
    empty = depth <= 0
    if empty.all() or not empty.any():
        return depth
    take = crack_pixels(~empty, cracks) if cracks > 0 else np.zeros_like(empty)
    limit = reach * max(depth.shape)
    if limit < 1:  # an empty pixel is at least 1 px from a covered one: the cracks alone
        return _nearest_within(depth, ~empty, take, cracks) if take.any() else depth
    from scipy.ndimage import distance_transform_edt

    dist, (iy, ix) = distance_transform_edt(empty, return_indices=True)
    take |= empty & (dist <= limit)
    out = depth.copy()
    out[take] = depth[iy[take], ix[take]]
    return out


def _nearest_within(depth: np.ndarray, covered: np.ndarray, take: np.ndarray, radius: int) -> np.ndarray:
    """``depth # [H, W]`` with each pixel of ``take # [H, W]`` bool given the z-depth of a nearest pixel of
    ``covered # [H, W]`` bool, searched among the offsets at most ``radius * sqrt(2)`` px away in increasing distance,
    ties in :func:`nearest_depth`'s order (the nearest lies there when one lies within ``radius`` px along each axis,
    as :func:`crack_pixels` ensures).
    ``# [H, W]``"""
    H, W = depth.shape
    ys, xs = np.nonzero(take)  # [n]
    value = np.zeros(len(ys), depth.dtype)  # [n]
    todo = np.arange(len(ys))
    r = np.arange(-2 * radius, 2 * radius + 1)
    dy, dx = (a.reshape(-1) for a in np.meshgrid(r, r, indexing="ij"))
    d2 = dy * dy + dx * dx
    order = np.lexsort((dy, dx, d2))  # nearest first; ties: the smaller column, then the smaller row
    order = order[(d2[order] > 0) & (d2[order] <= 2 * radius * radius)]
    for oy, ox in zip(dy[order], dx[order]):  # nearest first
        y, x = ys[todo] + oy, xs[todo] + ox
        ok = (y >= 0) & (y < H) & (x >= 0) & (x < W)
        hit = np.zeros(len(todo), bool)
        hit[ok] = covered[y[ok], x[ok]]
        value[todo[hit]] = depth[y[hit], x[hit]]
        todo = todo[~hit]
        if not len(todo):
            break
    out = depth.copy()
    out[ys, xs] = value
    return out


def nearest_fill(surface: Surface, covered: int, camera: Cameras, reach: float = NEAREST_FILL_REACH,
                 cracks: int = 0) -> tuple[Surface, Tensor]:
    """``surface`` (its first ``covered`` pixels on the mesh, the rest e.g. :func:`with_fill`'s layer) with the
    rest's points within ``reach`` or in a crack of radius ``cracks`` (:func:`nearest_depth`) moved onto their rays at
    the nearest covered pixel's z-depth. Returns the surface (float32 points) and which rows moved ``# [P]`` bool."""
    points, moved = surface.points.float().clone(), torch.zeros(len(surface.pixels), dtype=torch.bool)
    if covered == 0 or covered == len(surface.pixels):
        return replace(surface, points=points), moved
    H, W = surface.height, surface.width
    z = np.zeros(H * W, np.float32)
    z[surface.pixels[:covered].numpy()] = surface.depth[:covered].float().numpy()
    filled = torch.from_numpy(nearest_depth(z.reshape(H, W), reach, cracks).reshape(-1))
    holes = surface.pixels[covered:]
    rows = covered + (filled[holes] > 0).nonzero()[:, 0]
    px = surface.pixels[rows]
    zh = filled[px]  # [n]
    uv = torch.stack([(px % W).float() + 0.5, (px // W).float() + 0.5], -1)  # pixel centres
    points[rows] = camera.to(dtype=torch.float32).unproject(uv[None], zh[None])[0]
    moved[rows] = True
    depth = surface.depth.clone()
    depth[rows] = zh.to(depth.dtype)
    return replace(surface, points=points, depth=depth), moved


def shaded_surface(surface: Surface, camera: Cameras, far: float, bounds: Tensor | None, fill: str,
                   cracks: int = 0) -> tuple[Surface, int, Tensor]:
    """The pixels the mesh path shades in one view: ``surface`` (the mesh's pixels, its first rows), then the pixels
    it misses: with ``fill`` ``"far"`` or ``"nearest"`` all of them, on the background layer (:func:`with_fill`;
    ``"nearest"``: those within :data:`NEAREST_FILL_REACH` moved to the nearest covered pixel's z-depth), with
    ``"background"`` none; with ``cracks`` > 0, in every case the cracks (:func:`crack_pixels`) at the nearest covered
    pixel's z-depth. Returns the surface (float32 points), the count of its first rows on the mesh and which rows lie
    on the background layer ``# [P]`` bool (they skip the occlusion test: every source that frames them blends)."""
    covered = len(surface.pixels)
    if fill == "background" and cracks <= 0:
        return replace(surface, points=surface.points.float()), covered, torch.zeros(covered, dtype=torch.bool)
    surf, covered = with_fill(surface, camera, far, bounds)
    surf, moved = nearest_fill(surf, covered, camera, NEAREST_FILL_REACH if fill == "nearest" else 0.0, cracks)
    layer = (torch.arange(len(surf.pixels)) >= covered) & ~moved  # [P]
    if fill == "background":  # no layer: the cracks only
        keep = ~layer
        surf = replace(surf, pixels=surf.pixels[keep], points=surf.points[keep], depth=surf.depth[keep])
        layer = layer[keep]
    return surf, covered, layer
