"""Plane-sweep stereo for views that cannot be rectified against a sideways neighbour (a walk's photos).

Rectified stereo (:mod:`omnirecon.mesh.stereo`) needs a baseline across the optical axis: when the camera moves
along its view direction (a street walked forward, a phone carried down a corridor) the epipole lies inside the
image and no pair can be rectified sideways. A plane sweep needs no rectification (Collins 1996; the idea behind
COLMAP's and OpenMVS's multi-view stereo): for each of ``planes`` depths, uniform in inverse depth over the part of
the scene bounds the view sees, every neighbour is warped onto the view through the homography of the
fronto-parallel plane at that depth (OpenCV ``warpPerspective``), and the windowed zero-mean normalised
cross-correlation (ZNCC) with the view scores the depth; a pixel's cost at a depth is the mean of its ``best``
lowest neighbour costs (a neighbour that does not see the point, whose window falls on its black border or on an
occluder, correlates poorly and loses its vote). The lowest cost wins, refined by a
parabola through its two neighbours (in inverse depth).

A pixel keeps its depth only where the match is distinct: the reference window has texture (grey-level standard
deviation at least ``min_texture``), the winning ZNCC is at least ``min_zncc``, and some depth scores at least
``contrast`` worse than the winner (where every depth warps the neighbours to nearly the same window, as at the epipole
of a window without texture, the cost is flat: no depth). Its confidence is the winning ZNCC. Fusion's consistency check across views does the
rest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError


@dataclass
class SweepOptions:
    """Settings of :func:`sweep_depth`."""

    neighbours: int = 4
    """Views warped onto each view: its nearest by camera centre whose optical axes lie within ``max_view_angle``."""
    max_view_angle: float = 45.0
    """Degrees between optical axes beyond which a view is not a neighbour."""
    side: int = 320
    """The sweep runs on the photos downscaled to at most this long side (pixels; area averaging) and its depth is
    read back at the photos' own pixels (nearest sample); 0 = the photos' size."""
    planes: int = 64
    """Most depths tested, uniform in inverse depth: one per pixel of the largest shift between the nearest and the
    farthest depth in any neighbour (:func:`pixel_span`), at least 16."""
    window: int = 9
    """ZNCC window side in pixels (odd)."""
    best: int = 2
    """A pixel's cost at a depth: the mean of its this many lowest neighbour costs."""
    min_texture: float = 0.02
    """Least grey-level standard deviation (0-1) over the window for a pixel to get a depth."""
    min_zncc: float = 0.6
    """Least winning ZNCC for a pixel to get a depth."""
    contrast: float = 0.1
    """Least difference between a pixel's worst and best cost over the depths: where every depth warps the neighbours
    to nearly the same place (near the epipole, or a flat colour) the depth is not observable."""

    def check(self) -> None:
        if not (1 <= self.neighbours <= 16 and 1 <= self.best <= self.neighbours and 8 <= self.planes <= 512):
            raise InputError(f"sweep neighbours {self.neighbours}, best {self.best}, planes {self.planes} out of range",
                             None, "use e.g. 4, 2 and 96")
        if not (3 <= self.window <= 31 and self.window % 2 == 1):
            raise InputError(f"sweep window must be odd in 3-31, got {self.window}", None, "use e.g. 9")
        if not all(math.isfinite(v) and v >= 0 for v in (self.min_texture, self.min_zncc, self.contrast,
                                                          self.max_view_angle)):
            raise InputError("sweep thresholds must be finite and >= 0", None, "use the defaults")


def sweep_neighbours(cameras: Cameras, views: list[int], view: int, options: SweepOptions) -> list[int]:
    """The ``options.neighbours`` views of ``views`` nearest to ``view`` by camera centre (other than itself and any
    at its very centre) whose optical axes lie within ``options.max_view_angle`` of its own."""
    cams = cameras.to(dtype=torch.float64)
    others = [v for v in views if v != view]
    if not others:
        return []
    dist = (cams.centers[others] - cams.centers[view]).norm(dim=-1)
    cos = cams.forward[others] @ cams.forward[view]
    ok = (dist > 1e-9 * max(1.0, float(dist.max()))) & (cos >= math.cos(math.radians(options.max_view_angle)))
    order = [int(k) for k in torch.argsort(dist) if bool(ok[k])]
    return [others[k] for k in order[: options.neighbours]]


def depth_range(camera: Cameras, bounds: Tensor, near: float, far: float) -> tuple[float, float]:
    """The z-depths over which the view's rays cross ``bounds # [2, 3]`` (a 17x17 grid of pixel rays, the border
    included; slab test), within ``[near, far]``."""
    cam = camera.to(dtype=torch.float64)
    u = torch.linspace(0, cam.width, 17, dtype=torch.float64)
    v = torch.linspace(0, cam.height, 17, dtype=torch.float64)
    uv = torch.stack(torch.meshgrid(u, v, indexing="xy"), -1).reshape(1, -1, 2)
    o, d = cam.rays(uv, normalize=False)  # t along d is the z-depth
    o, d = o[0], d[0]
    inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t0, t1 = (bounds[0].double() - o) * inv, (bounds[1].double() - o) * inv
    enter, leave = torch.minimum(t0, t1).amax(-1), torch.maximum(t0, t1).amin(-1)
    hit = leave > enter.clamp_min(0)
    if not hit.any():
        return near, far
    lo = max(near, float(enter[hit].clamp_min(0).min()))
    hi = min(far, float(leave[hit].max()))
    return (lo, hi) if hi > lo > 0 else (near, far)


def pixel_span(cameras: Cameras, view: int, others: list[int], z_range: tuple[float, float]) -> float:
    """The largest shift, in pixels, between where a point at the nearest and at the farthest depth of ``z_range``
    behind the view's centre and corner pixels lands in any of ``others``."""
    cams = cameras.to(dtype=torch.float64)
    W, H = cams.width, cams.height
    uv = torch.tensor([[[W / 2, H / 2], [0, 0], [W, 0], [0, H], [W, H]]], dtype=torch.float64)
    near = cams[view].unproject(uv, torch.full((1, 5), z_range[0], dtype=torch.float64))[0]
    far = cams[view].unproject(uv, torch.full((1, 5), z_range[1], dtype=torch.float64))[0]
    span = 0.0
    for j in others:
        a, b = cams[j].project(near), cams[j].project(far)
        ok = a.in_front[0] & b.in_front[0]
        if ok.any():
            span = max(span, float((a.uv[0] - b.uv[0]).norm(dim=-1)[ok].max()))
    return span


def _grey(image: Tensor) -> np.ndarray:
    return (image.float().cpu().numpy() @ np.array([0.299, 0.587, 0.114], np.float32)).astype(np.float32)


def sweep_depth(images: Tensor, cameras: Cameras, view: int, others: list[int], z_range: tuple[float, float],
                options: SweepOptions | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Plane-sweep z-depth and confidence of ``view`` against ``others`` (module docstring); ``images # [N, H, W, 3]``
    in [0, 1]. ``# [H, W]`` float32 each (0 = no depth)."""
    import cv2

    options = options or SweepOptions()
    cams = cameras.to(dtype=torch.float64)
    H, W = cams.height, cams.width
    if not others:
        return np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)
    win = (options.window, options.window)

    def box(x):
        return cv2.boxFilter(x, -1, win, normalize=True, borderType=cv2.BORDER_REFLECT)

    ref = _grey(images[view])
    mu_r = box(ref)
    sd_r = np.sqrt(np.maximum(box(ref * ref) - mu_r * mu_r, 0.0))
    grey = {j: _grey(images[j]) for j in others}
    planes = int(np.clip(math.ceil(pixel_span(cameras, view, others, z_range)), 16, options.planes))
    inv_depths = np.linspace(1.0 / z_range[0], 1.0 / z_range[1], planes)
    K_i_inv = torch.linalg.inv(cams.K[view]).numpy()
    w2c_i = cams.w2c[view].numpy()
    c2w_i = np.linalg.inv(w2c_i)
    cost = np.empty((planes, H, W), np.float32)
    A = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])  # pixel index -> pixel coordinate (+0.5)
    A_inv = np.linalg.inv(A)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    for p, inv_z in enumerate(inv_depths):
        per = np.empty((len(others), H, W), np.float32)
        for k, j in enumerate(others):
            T = cams.w2c[j].numpy() @ c2w_i  # camera i -> camera j
            Hm = A_inv @ cams.K[j].numpy() @ (T[:3, :3] + np.outer(T[:3, 3], [0.0, 0.0, inv_z])) @ K_i_inv @ A
            warped = cv2.warpPerspective(grey[j], Hm, (W, H), flags=flags, borderValue=0.0)
            mu_w = box(warped)
            var_w = cv2.subtract(box(cv2.multiply(warped, warped)), cv2.multiply(mu_w, mu_w))
            cross = cv2.subtract(box(cv2.multiply(ref, warped)), cv2.multiply(mu_r, mu_w))
            zncc = cv2.divide(cross, cv2.max(cv2.multiply(sd_r, cv2.sqrt(cv2.max(var_w, 0.0))), 1e-6))
            per[k] = 1.0 - zncc
        if options.best < len(others):
            per = np.partition(per, options.best - 1, axis=0)[: options.best]
        cost[p] = per.mean(0)
    best = cost.argmin(0)  # [H, W]
    c_best = np.take_along_axis(cost, best[None], 0)[0]
    rows, cols = np.indices((H, W))
    lo, hi = np.clip(best - 1, 0, planes - 1), np.clip(best + 1, 0, planes - 1)
    c_lo, c_hi = cost[lo, rows, cols], cost[hi, rows, cols]
    denom = c_lo - 2 * c_best + c_hi
    inner = (denom > 1e-9) & (best > 0) & (best < planes - 1)
    shift = np.where(inner, 0.5 * (c_lo - c_hi) / np.where(inner, denom, 1.0), 0.0)
    step = inv_depths[1] - inv_depths[0]
    inv = inv_depths[best] + np.clip(shift, -0.5, 0.5) * step
    ok = (sd_r >= options.min_texture) & (1 - c_best >= options.min_zncc) & (cost.max(0) - c_best >= options.contrast)
    ok &= inv > 0
    depth = np.where(ok, 1.0 / np.where(inv > 0, inv, 1.0), 0.0).astype(np.float32)
    return depth, np.where(ok, np.clip(1 - c_best, 0, 1), 0.0).astype(np.float32)


def sweep_depths(images: Tensor, cameras: Cameras, views: list[int], all_views: list[int], bounds: Tensor,
                 near: Tensor, far: Tensor, options: SweepOptions | None = None, on_view=None) -> dict:
    """:func:`sweep_depth` at each of ``views``, against its :func:`sweep_neighbours` among ``all_views``, on the
    photos at ``options.side``: ``depth`` and ``confidence`` at the photos' pixels ``# [V, H, W]`` and the
    ``neighbours`` of each view."""
    import torch.nn.functional as F

    options = options or SweepOptions()
    options.check()
    H, W = cameras.height, cameras.width
    scale = min(1.0, options.side / max(H, W)) if options.side else 1.0
    small_cams, small = cameras, images
    if scale < 1.0:
        small_cams = cameras.rescaled(scale)
        h, w = small_cams.height, small_cams.width
        small = F.interpolate(images.permute(0, 3, 1, 2).float(), size=(h, w), mode="area").permute(0, 2, 3, 1)
    depths, confs, neighbours = [], [], []
    for v in views:
        others = sweep_neighbours(cameras, all_views, v, options)
        z = depth_range(cameras[v], bounds, float(near[v]), float(far[v]))
        d, c = sweep_depth(small, small_cams, v, others, z, options)
        if scale < 1.0:  # nearest sample: no depth blended across an outline
            d = F.interpolate(torch.from_numpy(d)[None, None], size=(H, W), mode="nearest")[0, 0].numpy()
            c = F.interpolate(torch.from_numpy(c)[None, None], size=(H, W), mode="nearest")[0, 0].numpy()
        depths.append(torch.from_numpy(d))
        confs.append(torch.from_numpy(c))
        neighbours.append(others)
        if on_view is not None:
            on_view()
    return {"depth": torch.stack(depths), "confidence": torch.stack(confs), "neighbours": neighbours}
