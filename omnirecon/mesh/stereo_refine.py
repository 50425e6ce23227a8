"""Photometric refinement of depth maps: a local plane sweep around each pixel's depth, scored by the other views.

Stereo's matching windows straddle object outlines: on a dark, weakly textured object before a bright
textured ground the ground's texture decides the match, so the object's depth comes out biased toward
the ground behind it (demo scene, voted stereo at the training views: the dark sphere and the cone come out
too far, about half their pixels by more than 1 %). :func:`refine_depths` tests, per pixel, the depth
scaled by ``1 + s`` for shifts ``s`` in ``[-span, span]`` and keeps the one whose colour the neighbouring
views agree with best:

* the photometric cost of a pixel against neighbour ``j`` is the L1 colour difference between the view
  and ``j`` sampled (bilinear) where the pixel's 3-D point projects, truncated at ``truncate``;
* costs are aggregated over a ``window`` with *adaptive support weights* (Yoon and Kweon 2006: each
  window pixel weighs ``exp(-colour difference to the centre / colour_sigma - distance / space_sigma)``),
  so a dark pixel's window ignores the bright ground beside it; window pixels take their own depth
  scaled by the same ``1 + s`` (the map's local shape is kept, no fronto-parallel assumption);
* per shift, the mean of the ``best`` lowest costs over the neighbours (a neighbour that does not see the
  point loses its vote), then the arg-min with a parabola through its two neighbours (sub-step);
* before the sweep, each pixel is offered the depths of the pixels ``propagate`` px around it and keeps the one
  the photos agree with best by the same cost (:func:`propagated`, PatchMatch's spatial propagation): the ground
  beside an object's base that stereo gave the object's depth takes the ground's depth from a pixel farther out.

Pixels without depth stay without; the shift ``0`` is one of the tested ones, so a pixel only moves
when some other depth explains the photos better. Gross errors away from outlines (the ground's depth inside an
object, > 6 %) are out of its reach: fusion's consistency and occlusion checks deal with those.

On the demo scene (``MeshOptions.refine``) it shrinks the voted maps' median bias at the training views on the
sphere, the cone and the ground, and raises the held-out mesh path at ``--nearest 6`` (the dark cone and the sphere
most), but lowers the box (more so at a larger ``span``; the box is not less textured than the cone by the weighted
colour spread of its windows, so no texture test separates it).
Only the pixels with depth are scored, each window gathered from their rows (the pixels without depth weigh
nothing in a window): the same costs as a dense pass over the image, bit for bit, at a cost that follows the pixels
with depth. The stereo maps come here without the scene's known background colour (``MeshOptions.drop_background``),
so a scene with few pixels of depth (NeRF-synthetic's lego) costs a fraction of a dense pass.
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
    """Largest relative depth change tested (each side). On the demo scene 0.03-0.04 scored best on the held-out
    whole image; larger spans lowered the box."""
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
    before the sky). Keeping them scored lower on the demo scene's held-out whole image."""
    min_gain: float = 0.0
    """Move a pixel only where the best shift's cost is at least this much below the unshifted depth's
    (flat cost curves of untextured faces keep their depth)."""
    propagate: int = 2
    """Before the sweep, offer each pixel the depths of the pixels this far away (pixels; in 8 directions, and at
    half the distance) and keep the one its photo agrees with best (PatchMatch's spatial propagation; 0 = off):
    reaches the gross errors at outlines that the sweep cannot, e.g. the ground beside an object's base that stereo
    gave the object's depth. On the demo scene the exact depth within 3 px of the label outlines alone (a
    diagnostic) recovered most of the gap to the exact mesh: the loss is at outlines. 2 px scored best of 1, 2, 4 and
    8 px on the demo scene's held-out whole image; on two procedural scenes the pixels the mesh covers rose too
    while the whole image moved within what near-identical settings of the pipeline scatter on one scene
    (stereo+model, ``python -m bench depth_sources`` scoring). It doubles the refinement's cost; refining the
    model-filled maps too (``MeshOptions.refine="all"``) scored lower."""
    propagate_passes: int = 1
    """Passes of that propagation (each pass offers the depths the previous one chose: errors wider than the
    distance are reached)."""
    propagate_borders: bool = True
    """Propagate into pixels within the distance of a pixel without depth too (the map's borders: the ground's
    far edge before the sky, objects before the sky). ``False`` lowered the demo scene and raised one procedural
    scene; on is the default."""
    propagate_gain: float = 0.02
    """A propagated depth replaces the pixel's own only where its cost is lower by at least this much."""

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
        if not (0 <= self.propagate <= 16 and self.propagate_passes >= 1 and math.isfinite(self.propagate_gain)
                and self.propagate_gain >= 0):
            bad.append(("propagate/propagate_passes/propagate_gain",
                        (self.propagate, self.propagate_passes, self.propagate_gain),
                        "propagate in 0-16 px, at least one pass and a gain >= 0, e.g. 2, 1 and 0.02"))
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


class _Scorer:
    """The window cost of candidate depth maps of one view against its neighbours (module docstring)."""

    def __init__(self, images: Tensor, cameras: Cameras, view: int, valid: Tensor, others: list[int],
                 options: RefineOptions):
        H, W = valid.shape
        w = options.window
        self.options, self.H, self.W = options, H, W
        self.ref = images[view].float()  # [H, W, 3]
        flat = valid.reshape(-1)
        self.at = flat.nonzero()[:, 0]  # [P] the pixels with depth: the only ones scored or aggregated over
        slot = torch.full((H * W + 1,), len(self.at), dtype=torch.long)  # pixel -> its row in at (len: none)
        slot[self.at] = torch.arange(len(self.at))
        # each scored pixel's window, row-major as F.unfold orders it, as rows of at (len(at): outside / no depth)
        r, c = self.at // W, self.at % W
        offs = torch.arange(w) - w // 2
        wy = (r[None, :] + offs.repeat_interleave(w)[:, None])  # [w*w, P]
        wx = (c[None, :] + offs.repeat(w)[:, None])
        inside = (wy >= 0) & (wy < H) & (wx >= 0) & (wx < W)
        self.window = torch.where(inside, slot[(wy.clamp(0, H - 1) * W + wx.clamp(0, W - 1))], len(self.at))  # [w*w, P]
        self.window_flat = self.window.reshape(-1)  # [w*w P] for index_select (the same values as c[:, window])
        weights = support_weights(self.ref, options)[:, self.at]  # [w*w, P]
        self.weights = weights * (self.window < len(self.at))  # window pixels with depth only
        self.norm = self.weights.sum(0).clamp_min(1e-8)  # [P]
        cam = cameras[view].to(dtype=torch.float32)
        v, u = (r.float() + 0.5), (c.float() + 0.5)
        rays = torch.stack([(u - cam.cx[0]) / cam.fx[0], (v - cam.cy[0]) / cam.fy[0], torch.ones_like(u)], -1)
        self.rays = rays @ cam.R[0].T  # [P, 3] world direction with camera z = 1
        self.ref_at = self.ref.reshape(-1, 3)[self.at].T[None]  # [1, 3, P]
        self.centre = cam.centers[0]
        self.oc = cameras[others].to(dtype=torch.float32)
        self.proj = self.oc.K @ self.oc.w2c[:, :3, :]  # [J, 3, 4]
        self.src = images[others].float().permute(0, 3, 1, 2)  # [J, 3, H, W]
        self.size = torch.tensor([self.oc.width, self.oc.height], dtype=torch.float32)

    def __call__(self, d: Tensor) -> Tensor:
        """Cost of the z-depth ``d # [HW]`` (each window pixel at its own depth in ``d``) at the pixels with depth;
        ``truncate`` at the others (never used: they have no depth to move). ``# [HW]``"""
        o = self.options
        pts = self.centre + self.rays * d[self.at][:, None]  # [P, 3]
        uvz = self.proj[:, :, :3] @ pts.T + self.proj[:, :, 3:]  # [J, 3, P]
        z = uvz[:, 2]
        uv = uvz[:, :2] / z.clamp_min(1e-6)[:, None]  # [J, 2, P]
        grid = (uv / self.size[None, :, None] * 2 - 1).permute(0, 2, 1)[:, None]  # [J, 1, P, 2]
        sampled = F.grid_sample(self.src, grid, mode="bilinear", padding_mode="border", align_corners=False)[:, :, 0]
        c = (sampled - self.ref_at).abs().sum(1).clamp_max(o.truncate)  # [J, P]
        seen = (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < self.oc.width) & (uv[:, 1] >= 0) & (uv[:, 1] < self.oc.height)
        c = torch.where(seen, c, torch.full_like(c, o.truncate))
        c = torch.cat([c, torch.zeros_like(c[:, :1])], 1)  # [J, P + 1]: the last column for window pixels without depth
        windows = c.index_select(1, self.window_flat).view(len(c), *self.window.shape)  # [J, w*w, P]
        agg = windows.mul_(self.weights).sum(1) / self.norm  # [J, P]
        out = torch.full((self.H * self.W,), float(o.truncate))
        out[self.at] = lowest_mean(agg, o.best)
        return out


def lowest_mean(costs: Tensor, k: int) -> Tensor:
    """Mean of the ``k`` lowest of ``costs # [J, P]`` over ``J``, as ``costs.sort(0).values[:k].mean(0)`` computes it
    (bit for bit): for ``k`` of 1 and 2 by running minima (a sort over the first dimension cost more than the window
    sums it follows). ``# [P]``"""
    if k == 1:
        return costs.amin(0)
    if k == 2 and len(costs) >= 2:
        lo = torch.minimum(costs[0], costs[1])
        second = torch.maximum(costs[0], costs[1])
        for c in costs[2:]:
            second = torch.minimum(second, torch.maximum(lo, c))
            lo = torch.minimum(lo, c)
        return (lo + second) / 2
    return costs.sort(0).values[:k].mean(0)


def propagated(score: _Scorer, depth: Tensor, options: RefineOptions) -> Tensor:
    """``depth # [H, W]`` where each pixel with depth may take the depth of a pixel ``options.propagate`` (or half
    that) pixels away in one of 8 directions, when its photo agrees with that depth better by
    ``options.propagate_gain`` (:class:`_Scorer`). ``# [H, W]``"""
    H, W = depth.shape
    valid = depth > 0
    best_d = depth.reshape(-1)
    own = score(best_d)
    best_c = own.clone()
    r = options.propagate
    for step in sorted({max(1, r // 2), r}):
        for dy in (-step, 0, step):
            for dx in (-step, 0, step):
                if dx == 0 and dy == 0:
                    continue
                cand = torch.zeros_like(depth)
                ys, yd = slice(max(dy, 0), H + min(dy, 0)), slice(max(-dy, 0), H + min(-dy, 0))
                xs, xd = slice(max(dx, 0), W + min(dx, 0)), slice(max(-dx, 0), W + min(-dx, 0))
                cand[yd, xd] = depth[ys, xs]  # cand[p] = depth[p + (dy, dx)]
                cand = torch.where((cand > 0) & valid, cand, depth).reshape(-1)
                c = score(cand)
                better = c < best_c
                best_c = torch.where(better, c, best_c)
                best_d = torch.where(better, cand, best_d)
    keep = best_c <= own - options.propagate_gain
    if not options.propagate_borders:  # every pixel within the distance has depth
        hole = F.max_pool2d((~valid)[None, None].float(), 2 * r + 1, stride=1, padding=r)[0, 0] > 0
        keep = keep & ~hole.reshape(-1)
    return torch.where(keep, best_d, depth.reshape(-1)).reshape(H, W)


def refine_view(images: Tensor, cameras: Cameras, view: int, depth: Tensor, others: list[int],
                options: RefineOptions) -> Tensor:
    """``depth # [H, W]`` (0 = none) of ``view`` refined against ``others`` (module docstring). ``# [H, W]``"""
    H, W = depth.shape
    valid = depth > 0
    score = _Scorer(images, cameras, view, valid, others, options)
    for _ in range(options.propagate_passes if options.propagate > 0 else 0):
        depth = propagated(score, depth, options)
    shifts = torch.linspace(-options.span, options.span, options.steps)
    d = depth.reshape(-1)
    costs = [score(d * (1 + s)) for s in shifts]
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
