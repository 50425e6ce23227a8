"""The mesh path's fill: a background layer for pixels no triangle covers (``MeshRenderOptions.fill``).

A pixel the mesh misses is given the point where its ray leaves the scene's bounds box (the box's far
side), never farther than the sources' far z-depth; the mesh renderer then shades it with the same
image-based blend as the surface, so no pixel is left at a background colour.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.render.raster import Surface


def fill_points(camera: Cameras, pixels: Tensor, far: float, bounds: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The background layer at flat pixel indices ``pixels # [M]`` of one camera: where each pixel-centre
    ray leaves the box ``bounds # [2, 3]`` (its far side), at most at z-depth ``far`` (rays that miss the
    box, or no box: at ``far``). Returns world ``points # [M, 3]`` and their z-depths ``# [M]`` (float32)."""
    uv = camera.pixel_centers().reshape(-1, 2)[pixels.to(camera.device)]  # [M, 2]
    o, d = camera.rays(uv[None], normalize=False)  # [1, M, 3]: origin + z * d is at z-depth z
    o, d = o[0].double(), d[0].double()
    z = torch.full((len(uv),), float(far), dtype=torch.float64, device=o.device)
    if bounds is not None:
        b = bounds.to(o)
        safe = torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
        t1, t2 = (b[0] - o) / safe, (b[1] - o) / safe  # [M, 3]
        t_in, t_out = torch.minimum(t1, t2).amax(-1), torch.maximum(t1, t2).amin(-1)  # [M]
        hit = (t_out > t_in.clamp_min(0)) & (t_out > 0)
        z = torch.where(hit, torch.minimum(t_out, z), z)
    return (o + z[:, None] * d).float(), z.float()


def with_fill(surface: Surface, camera: Cameras, far: float, bounds: Tensor | None = None) -> tuple[Surface, int]:
    """``surface`` plus the background layer (:func:`fill_points`) at every pixel it does not cover; the
    first returned count of pixels are the real surface's."""
    covered = torch.zeros(surface.height * surface.width, dtype=torch.bool)
    covered[surface.pixels] = True
    miss = (~covered).nonzero()[:, 0]
    if not len(miss):
        return surface, len(surface.pixels)
    points, depth = fill_points(camera, miss, far, bounds)
    return replace(surface, pixels=torch.cat([surface.pixels, miss]), points=torch.cat([surface.points, points]),
                   depth=torch.cat([surface.depth, depth])), len(surface.pixels)
