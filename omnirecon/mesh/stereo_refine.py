"""Photometric refinement of depth maps: a local plane sweep around each pixel's depth, scored by the other views.

Stereo's matching windows straddle object outlines: on a dark, weakly textured object before a bright
textured ground the ground's texture decides the match, so the object's depth comes out biased toward
the ground behind it (demo scene, voted stereo at the training views: the dark sphere +1.4 % median, the
cone +0.7 %, half their pixels more than 1 % off). :func:`refine_depths` tests, per pixel, the depth
scaled by ``1 + s`` for shifts ``s`` in ``[-span, span]`` and keeps the one whose colour the neighbouring
views agree with best:

* the photometric cost of a pixel against neighbour ``j`` is the L1 colour difference between the view
  and ``j`` sampled (bilinear) where the pixel's 3-D point projects, truncated at ``truncate``;
* costs are aggregated over a ``window`` with *adaptive support weights* (Yoon and Kweon 2006: each
  window pixel weighs ``exp(-colour difference to the centre / colour_sigma - distance / space_sigma)``),
  so a dark pixel's window ignores the bright ground beside it; window pixels take their own depth
  scaled by the same ``1 + s`` (the map's local shape is kept, no fronto-parallel assumption);
* per shift, the mean of the ``best`` lowest costs over the neighbours (a neighbour that does not see the
  point loses its vote), then the arg-min with a parabola through its two neighbours (sub-step).

Pixels without depth stay without; the shift ``0`` is one of the tested ones, so a pixel only moves
when some other depth explains the photos better. Gross errors (the ground's depth on an object, > 6 %)
are out of its reach: fusion's consistency and occlusion checks deal with those.

Measured on the demo scene (``MeshOptions.refine``, where the numbers are): the voted maps' median bias
at the training views, sphere +1.37 -> +0.28 %, cone +0.69 -> +0.33 %, ground +0.23 -> +0.08 %; the held-out
mesh path at ``--nearest 6`` 25.64 -> 25.99 dB whole image, the dark cone 15.39 -> 17.85 dB, sphere 21.10 ->
24.12, but the box 22.13 -> 21.73 dB (at ``span`` 0.06 the box fell to 19.89; with the box's pixels left
unrefined, a diagnostic that reads the scene's labels, box 21.36 and whole 26.12 at 0.06: the box is not less
textured than the cone by the weighted colour spread of its windows, so no texture test separates it).
A few CPU-s for 18 views of 128 px.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError


@dataclass
class RefineOptions:
    """Settings of :func:`refine_depths`."""

    span: float = 0.04
    """Largest relative depth change tested (each side). Demo scene, held-out whole image at ``--nearest 6``
    (box): 0.02 25.95 dB (21.94), 0.03 26.00 (21.39), 0.04 25.99 (21.73), 0.06 25.92 (19.89); none 25.64 (22.13)."""
    steps: int = 17
    """Shifts tested over ``[-span, span]`` (odd, so that 0 is one of them; 0.5 % apart by default)."""
    neighbours: int = 4
    """Views scoring each view: the nearest by viewing direction."""
    best: int = 2
    """Per shift, the mean of this many lowest neighbour costs (occlusion: a neighbour that does not see
    the point loses its vote)."""
    window: int = 5
    """Side of the aggregation window in pixels (odd)."""
    colour_sigma: float = 0.1
    """Adaptive support weight: colour (L1 over RGB in [0, 1]) falloff."""
    space_sigma: float = 3.5
    """Adaptive support weight: distance (pixels) falloff."""
    truncate: float = 0.3
    """Per-pixel cost cap (L1 over RGB)."""
    keep_borders: bool = False
    """Keep the depth of pixels next to a pixel without depth (the map's borders, e.g. the ground's edge
    before the sky). Demo scene, held-out whole image at ``--nearest 6``: 25.92 dB without, 25.81 with."""
    min_gain: float = 0.0
    """Move a pixel only where the best shift's cost is at least this much below the unshifted depth's
    (flat cost curves of untextured faces keep their depth)."""

    def check(self) -> None:
        bad = []
        if not (math.isfinite(self.span) and 0 < self.span < 0.5):
            bad.append(("span", self.span, "a relative depth change in (0, 0.5), e.g. 0.04"))
        if not (3 <= self.steps <= 101 and self.steps % 2 == 1):
            bad.append(("steps", self.steps, "an odd integer in 3-101, e.g. 17"))
        if not 1 <= self.best <= self.neighbours <= 16:
            bad.append(("best/neighbours", (self.best, self.neighbours), "1 <= best <= neighbours <= 16, e.g. 2 and 4"))
        if not (1 <= self.window <= 15 and self.window % 2 == 1):
            bad.append(("window", self.window, "an odd integer in 1-15, e.g. 5"))
        if not (self.colour_sigma > 0 and self.space_sigma > 0 and self.truncate > 0):
            bad.append(("colour_sigma/space_sigma/truncate", (self.colour_sigma, self.space_sigma, self.truncate),
                        "positive numbers, e.g. 0.1, 3.5 and 0.3"))
        if bad:
            name, value, fix = bad[0]
            raise InputError(f"refine option {name} = {value} is out of range", None, f"use {fix}")


def nearest_by_direction(cameras: Cameras, views: list[int], k: int) -> list[list[int]]:
    """For each of ``views``, the ``k`` other views of ``views`` whose optical axes are closest to its own."""
    z = cameras.to(dtype=torch.float64).forward[views]  # [V, 3]
    cos = z @ z.T
    cos.fill_diagonal_(-2.0)
    order = torch.argsort(cos, dim=1, descending=True)[:, :k]
    return [[views[int(j)] for j in row] for row in order]


def support_weights(image: Tensor, options: RefineOptions) -> Tensor:
    """Adaptive support weights of ``image # [H, W, 3]``: each pixel's window, ``# [w*w, H*W]``."""
    w = options.window
    img = image.permute(2, 0, 1)[None]  # [1, 3, H, W]
    patches = F.unfold(img, w, padding=w // 2).reshape(3, w * w, -1)  # [3, w*w, HW]
    colour = (patches - img.reshape(3, 1, -1)).abs().sum(0)  # [w*w, HW]
    r = torch.arange(w, dtype=image.dtype) - w // 2
    dist = (r[:, None].square() + r[None, :].square()).sqrt().reshape(-1, 1)  # [w*w, 1]
    return torch.exp(-colour / options.colour_sigma - dist / options.space_sigma)


def refine_view(images: Tensor, cameras: Cameras, view: int, depth: Tensor, others: list[int],
                options: RefineOptions) -> Tensor:
    """``depth # [H, W]`` (0 = none) of ``view`` refined against ``others`` (module docstring). ``# [H, W]``"""
    H, W = depth.shape
    w = options.window
    valid = depth > 0
    ref = images[view].float()  # [H, W, 3]
    weights = support_weights(ref, options)  # [w*w, HW]
    inside = F.unfold(valid[None, None].float(), w, padding=w // 2)[0]  # [w*w, HW]: window pixels with depth
    weights = weights * inside
    norm = weights.sum(0).clamp_min(1e-8)  # [HW]
    cam = cameras[view].to(dtype=torch.float32)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32) + 0.5, torch.arange(W, dtype=torch.float32) + 0.5,
                          indexing="ij")
    rays = torch.stack([(u - cam.cx[0]) / cam.fx[0], (v - cam.cy[0]) / cam.fy[0], torch.ones_like(u)], -1)
    rays = rays.reshape(-1, 3) @ cam.R[0].T  # [HW, 3] world direction with camera z = 1
    centre = cam.centers[0]
    oc = cameras[others].to(dtype=torch.float32)
    proj = oc.K @ oc.w2c[:, :3, :]  # [J, 3, 4]
    src = images[others].float().permute(0, 3, 1, 2)  # [J, 3, H, W]
    size = torch.tensor([oc.width, oc.height], dtype=torch.float32)
    shifts = torch.linspace(-options.span, options.span, options.steps)
    d = depth.reshape(-1)
    costs = []
    for s in shifts:
        pts = centre + rays * (d * (1 + s))[:, None]  # [HW, 3]
        uvz = proj[:, :, :3] @ pts.T + proj[:, :, 3:]  # [J, 3, HW]
        z = uvz[:, 2]
        uv = uvz[:, :2] / z.clamp_min(1e-6)[:, None]  # [J, 2, HW]
        grid = (uv / size[None, :, None] * 2 - 1).permute(0, 2, 1)[:, None]  # [J, 1, HW, 2]
        sampled = F.grid_sample(src, grid, mode="bilinear", padding_mode="border", align_corners=False)[:, :, 0]  # [J, 3, HW]
        c = (sampled - ref.reshape(-1, 3).T[None]).abs().sum(1).clamp_max(options.truncate)  # [J, HW]
        seen = (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < oc.width) & (uv[:, 1] >= 0) & (uv[:, 1] < oc.height)
        c = torch.where(seen, c, torch.full_like(c, options.truncate))
        agg = (F.unfold(c.reshape(-1, 1, H, W), w, padding=w // 2) * weights[None]).sum(1) / norm  # [J, HW]
        costs.append(agg.sort(0).values[: options.best].mean(0))
    cost = torch.stack(costs)  # [S, HW]
    k = cost.argmin(0)  # [HW]
    lo, hi = (k - 1).clamp_min(0), (k + 1).clamp_max(options.steps - 1)
    c0, cl, ch = cost.gather(0, k[None])[0], cost.gather(0, lo[None])[0], cost.gather(0, hi[None])[0]
    denom = cl - 2 * c0 + ch
    inner = (k > 0) & (k < options.steps - 1) & (denom > 1e-9)
    frac = torch.where(inner, 0.5 * (cl - ch) / denom.clamp_min(1e-9), torch.zeros_like(c0)).clamp(-0.5, 0.5)
    step = 2 * options.span / (options.steps - 1)
    best = shifts[k] + frac * step
    if options.min_gain > 0:  # cost[steps // 2] is the unshifted depth's
        best = torch.where(cost[options.steps // 2] - c0 >= options.min_gain, best, torch.zeros_like(best))
    move = valid
    if options.keep_borders:  # every pixel of the 3x3 neighbourhood has depth
        move = move & (F.max_pool2d((~valid)[None, None].float(), 3, stride=1, padding=1)[0, 0] == 0)
    return torch.where(move, depth * (1 + best.reshape(H, W)), depth)


def refine_depths(images: Tensor, cameras: Cameras, views: list[int], depth: Tensor,
                  options: RefineOptions | None = None) -> Tensor:
    """Depth maps ``depth # [V, H, W]`` (0 = none) at ``views`` refined photometrically against each view's
    :func:`nearest_by_direction` views among ``views`` (module docstring). ``images # [N, H, W, 3]`` in [0, 1].
    ``# [V, H, W]``"""
    options = options or RefineOptions()
    options.check()
    views = list(views)
    near = nearest_by_direction(cameras, views, min(options.neighbours, len(views) - 1))
    out = []
    for a, (i, others) in enumerate(zip(views, near)):
        out.append(refine_view(images, cameras, i, depth[a].float(), others, options) if others else depth[a])
    return torch.stack(out)
