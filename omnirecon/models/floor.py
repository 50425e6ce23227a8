"""The non-learned floor every learned model must beat: plane-sweep photo-consistency.

For each target ray, ``num_depths`` candidate z-depths are projected into every source view; the
depth whose reprojected source colours agree best (lowest colour variance over the views that see
it, needing at least ``min_views``) wins, and the colour is the mean of those source colours.
Rays with no such candidate get the mean of every source colour seen along them (or grey), so
the floor never scores below a blur of the sources.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from omnirecon.models.base import Capabilities, GeneralizableModel
from omnirecon.models.projector import gather, project
from omnirecon.rays import Rays, Sources
from omnirecon.render.volume import sample_along_rays


@dataclass
class PlaneSweepConfig:
    num_views: int = 5
    """Source views used per target."""
    num_depths: int = 64
    """Depth candidates per ray."""
    min_views: int = 2
    """A candidate needs this many views that see it."""


PRESETS = {"floor": PlaneSweepConfig()}


@dataclass
class PlaneSweepFeatures:
    sources: Sources


class PlaneSweep(GeneralizableModel):
    capabilities = Capabilities(depth=True)

    def __init__(self, cfg: PlaneSweepConfig):
        super().__init__()
        self.cfg = cfg

    def encode(self, sources: Sources) -> PlaneSweepFeatures:
        return PlaneSweepFeatures(sources)

    def render_rays(self, features: PlaneSweepFeatures, rays: Rays) -> dict[str, Tensor]:
        src = features.sources
        cams = src.cameras
        R, S = len(rays), self.cfg.num_depths
        near = torch.full((R,), src.near, dtype=rays.origins.dtype, device=rays.origins.device)
        z = sample_along_rays(near, torch.full_like(near, src.far), S, inverse_depth=src.rig == "forward")  # [R, S]
        proj = project(cams, rays.points(z, unit_z=True))  # [R, S, 3] points
        rgb = gather(src.images.permute(0, 3, 1, 2), proj)  # [R, S, V, 3]
        m = proj.mask[..., None].to(rgb.dtype)  # [R, S, V, 1]
        count = m.sum(2)  # [R, S, 1]
        mean = (rgb * m).sum(2) / count.clamp_min(1)  # [R, S, 3]
        var = (((rgb - mean[:, :, None]) ** 2) * m).sum(2).sum(-1) / count[..., 0].clamp_min(1)  # [R, S]
        var = torch.where(count[..., 0] >= self.cfg.min_views, var, torch.full_like(var, float("inf")))
        best = var.argmin(-1)  # [R]
        ok = torch.isfinite(var.gather(1, best[:, None]))[:, 0]
        colour = mean.gather(1, best[:, None, None].expand(-1, 1, 3))[:, 0]
        seen = m.sum((1, 2))  # [R, 1]
        blur = torch.where(seen > 0, (rgb * m).sum((1, 2)) / seen.clamp_min(1), torch.full_like(colour, 0.5))
        colour = torch.where(ok[:, None], colour, blur)
        return {"rgb": colour, "depth": z.gather(1, best[:, None])[:, 0], "valid": ok}
