"""Volume rendering along rays: sampling, density weights and compositing.

Pure torch, differentiable, shape-agnostic over leading ray dimensions: ``R`` rays, ``S`` samples.
"""

from __future__ import annotations

import torch
from torch import Tensor


def sample_along_rays(near: Tensor, far: Tensor, num: int, inverse_depth: bool = False,
                      jitter: bool = False, generator: torch.Generator | None = None) -> Tensor:
    """Sample positions between ``near # [R]`` and ``far # [R]``. ``# [R, S]`` increasing.

    Uniform in depth, or in inverse depth (forward-facing scenes). ``jitter`` draws one uniform
    sample per interval (stratified sampling, for training); otherwise interval midpoints are not
    used: the samples include both ends, as the reference implementations do.
    """
    u = torch.linspace(0.0, 1.0, num, dtype=near.dtype, device=near.device).expand(near.shape[0], num)
    if jitter:
        step = 1.0 / max(num - 1, 1)
        u = (u + (torch.rand(u.shape, generator=generator, dtype=u.dtype).to(u.device) - 0.5) * step).clamp(0, 1)
        u = u.sort(dim=-1).values
    near, far = near[:, None], far[:, None]
    if inverse_depth:
        return 1.0 / (1.0 / near * (1 - u) + 1.0 / far * u)
    return near * (1 - u) + far * u


def alpha_from_density(sigma: Tensor, t: Tensor | None = None) -> Tensor:
    """Opacity per sample, ``1 - exp(-sigma * delta)``. ``# [R, S]``

    With ``t # [R, S]`` the interval ``delta`` is the distance to the next sample (the last one
    extends to infinity); ``t=None`` uses ``delta = 1`` (IBRNet's per-sample density).
    """
    if t is None:
        return 1.0 - torch.exp(-sigma)
    delta = torch.cat([t[..., 1:] - t[..., :-1], torch.full_like(t[..., :1], 1e10)], dim=-1)
    return 1.0 - torch.exp(-sigma * delta)


def sample_intervals(t: Tensor) -> Tensor:
    """Interval of each sample: the mean of its two neighbouring spacings, end spacings replicated. ``# [R, S]``"""
    gaps = t[..., 1:] - t[..., :-1]  # [R, S-1]
    gaps = torch.cat([gaps[..., :1], gaps, gaps[..., -1:]], -1)  # [R, S+1]
    return 0.5 * (gaps[..., 1:] + gaps[..., :-1])


def alpha_from_sdf(sdf: Tensor, t: Tensor, sharpness: Tensor | float) -> Tensor:
    """NeuS-style opacity of signed ray distances (VolRecon's variant, the slope fixed to -1). ``# [R, S]``

    ``sdf # [R, S]`` is positive in front of the surface and negative behind it, sampled at ray
    distances ``t # [R, S]`` (increasing). With ``Phi(x) = sigmoid(sharpness * x)`` and the interval
    ``delta`` of :func:`sample_intervals`, the SDF at the two ends of the sample's section is
    ``s +- delta / 2`` and
    ``alpha = clip((Phi(s + delta/2) - Phi(s - delta/2) + 1e-5) / (Phi(s + delta/2) + 1e-5), 0, 1)``:
    the fraction of the remaining "outside" mass lost across the section. A ray crossing
    ``sdf = t0 - t`` gets its weight peak at ``t0``. Use ``weights_from_alpha(alpha, eps=1e-7)`` as the reference.
    """
    half = 0.5 * sample_intervals(t)
    prev = torch.sigmoid((sdf + half) * sharpness)
    nxt = torch.sigmoid((sdf - half) * sharpness)
    return ((prev - nxt + 1e-5) / (prev + 1e-5)).clamp(0.0, 1.0)


def weights_from_alpha(alpha: Tensor, eps: float = 1e-10) -> tuple[Tensor, Tensor]:
    """Compositing weights ``w_i = alpha_i prod_{j<i} (1 - alpha_j + eps)`` and transmittance. ``# [R, S]`` each."""
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[..., :1]), 1.0 - alpha[..., :-1] + eps], -1), -1)
    return alpha * trans, trans


def composite(weights: Tensor, values: Tensor) -> Tensor:
    """``sum_s w_s v_s`` over samples: ``weights # [R, S]``, ``values # [R, S, C]`` -> ``# [R, C]``."""
    return (weights[..., None] * values).sum(-2)


def sample_pdf(bins: Tensor, weights: Tensor, num: int, deterministic: bool = True,
               generator: torch.Generator | None = None) -> Tensor:
    """Importance samples from the piecewise-constant PDF ``weights # [R, B-1]`` on ``bins # [R, B]``. ``# [R, num]``"""
    w = weights + 1e-5
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[..., :1]), torch.cumsum(pdf, -1)], -1)  # [R, B]
    if deterministic:
        u = torch.linspace(0.0, 1.0, num, dtype=bins.dtype, device=bins.device).expand(*cdf.shape[:-1], num)
    else:
        u = torch.rand(*cdf.shape[:-1], num, generator=generator, dtype=bins.dtype).to(bins.device)
    u = u.contiguous()
    idx = torch.searchsorted(cdf, u, right=True)
    lo = (idx - 1).clamp(0, cdf.shape[-1] - 1)
    hi = idx.clamp(0, cdf.shape[-1] - 1)
    cdf_lo, cdf_hi = cdf.gather(-1, lo), cdf.gather(-1, hi)
    bin_lo, bin_hi = bins.gather(-1, lo), bins.gather(-1, hi)
    denom = torch.where(cdf_hi - cdf_lo < 1e-5, torch.ones_like(cdf_lo), cdf_hi - cdf_lo)
    return bin_lo + (u - cdf_lo) / denom * (bin_hi - bin_lo)
