"""The hierarchical sampler of the models that render in two passes (IBRNet, Omni-Recon): coarse
z-depths between the sources' near and far bounds, then importance samples drawn from the coarse
pass's weights and merged with the coarse ones. The arithmetic lives in :mod:`omnirecon.render.volume`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from omnirecon.rays import Rays, Sources
from omnirecon.render.volume import sample_along_rays, sample_pdf


def coarse_depths(sources: Sources, rays: Rays, num: int, jitter: bool = False) -> Tensor:
    """``num`` z-depths per ray in ``[near, far]`` of ``sources``, uniform in inverse depth for forward-facing
    rigs; stratified when ``jitter``. ``# [R, num]``"""
    near = rays.origins.new_full((len(rays),), sources.near)
    far = rays.origins.new_full((len(rays),), sources.far)
    return sample_along_rays(near, far, num, inverse_depth=sources.rig == "forward", jitter=jitter)


def fine_depths(z: Tensor, weights: Tensor, num: int, jitter: bool = False, surface_samples: int = 0,
                origin: bool = False) -> Tensor | tuple[Tensor, Tensor]:
    """The coarse depths ``z # [R, S]`` plus ``num`` samples of the piecewise-constant density of
    ``weights # [R, S]`` between their midpoints (deterministic unless ``jitter``), sorted (the
    importance samples detached from the graph). ``# [R, S + num]``

    With ``surface_samples = n > 0`` and no ``jitter`` (rendering, depth maps), the fine pass gets only
    ``n`` deterministic importance samples, which gather around the coarse surface: no coarse depth is
    evaluated twice. ``# [R, n]`` (it changes the output: a quality/speed trade measured by
    ``bench/fast_paths.py``). With ``origin`` (and no ``surface_samples``) also which of the sorted depths
    are coarse ones. ``# [R, S + num]`` bool"""
    mid = 0.5 * (z[:, 1:] + z[:, :-1])
    if surface_samples > 0 and not jitter:
        return sample_pdf(mid, weights[:, 1:-1].detach(), surface_samples).detach()
    z_imp = sample_pdf(mid, weights[:, 1:-1].detach(), num, deterministic=not jitter)
    merged = torch.cat([z, z_imp.detach()], -1).sort(-1)
    return (merged.values, merged.indices < z.shape[1]) if origin else merged.values
