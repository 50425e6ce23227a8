"""Surface-guided volumetric rendering: each ray samples a narrow band around a depth prior plus a few guard
samples instead of marching the whole near-far range.

The prior is a z-depth map of the target view: given by the caller (a mesh rendered to depth, stereo depth) or,
by default, the model's own render at ``1 / prior_scale`` of the target's size, upsampled. A pixel's band spans the
prior depths of the 2x2 low-resolution cells around its centre (those bilinear upsampling blends), widened by
``band`` on each side, so that a pixel on a depth edge gets the whole step between the two surfaces; a pixel
whose cells spread wider than ``max_spread``, or touches a cell the prior does not trust (no value, opacity below
``min_opacity``, or the model's own ``valid`` False), has no prior and is rendered by the full path. Its reference
twin is the full path itself: :func:`render_guided` with ``GuidedOptions(on=False)`` is ``model.render_view``,
and the pixels without a prior are ``render_view(pixels=...)``, the same values as the full image's there
(``tests/models/test_guided.py`` checks both, and holds the guided render to a stated PSNR of the full one).

Units: band widths and spreads are fractions of the near-far range measured in the parameter the models sample
uniformly: inverse depth on forward-facing rigs (``Sources.rig == "forward"``), z-depth otherwise (so 0 is the
near bound and 1 the far one, and a band of 0.05 is 1/20 of the range a full ray covers).

What changes per model (``Capabilities.guided``: ``render_rays(features, rays, depths=z)`` renders one pass at
the caller's sample depths): GPNR attends along its ray over the given points instead of its linear ones;
IBRNet and Omni-Recon render their final pass (IBRNet's fine network unless ``fine_pass=False``) on them, with
no coarse pass. Guided rendering changes the output: it is a render option with its PSNR cost measured by
``python -m bench guided``, not a fast path with a bit-exact twin.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from omnirecon.cameras import Cameras


@dataclass
class GuidedOptions:
    """Surface-guided rendering (off by default)."""

    on: bool = False
    """Render each ray with prior from ``band_samples + guard_samples`` samples around its prior depth; rays
    without a prior (or with one the prior does not trust) take the full path. Off: the full path everywhere."""
    prior_scale: int = 4
    """Without a given prior, the model renders the view at ``1 / prior_scale`` of its width and height with its
    full path (``prior_scale ** 2`` times fewer rays) and its depth, upsampled, is the prior."""
    band_samples: int | None = None
    """Samples per ray spread evenly over the band (the 2x2 prior cells' depths plus ``band`` on each side).
    None: the model family's value in :data:`FAMILY_DEFAULTS`."""
    guard_samples: int | None = None
    """Samples per ray at the centres of this many equal cells of the whole near-far range (in the sampling
    parameter), merged with the band's: the model sees some of the space in front of and behind the band.
    None: the model family's value in :data:`FAMILY_DEFAULTS`."""
    band: float | None = None
    """Half-width added on each side of a pixel's prior depths, as a fraction of the near-far range in the
    sampling parameter (inverse depth on forward-facing rigs, z-depth otherwise). None: the model family's value
    in :data:`FAMILY_DEFAULTS`."""
    max_spread: float = 0.25
    """A pixel whose 2x2 prior cells span more than this fraction of the near-far range (sampling
    parameter) has no prior: full sampling there (depth edges wider than the band could cover)."""
    min_opacity: float = 0.5
    """Models that report opacity (``acc``: IBRNet, Omni-Recon): prior pixels below it are not trusted, and a
    guided ray below it (its band found no surface) is rendered again by the full path. Models without ``acc``
    (GPNR) trust every ``valid`` prior pixel."""

    def check(self) -> None:
        """InputError naming the first option out of its range (its rules: ``guided.*`` in ``omnirecon.options``)."""
        from omnirecon.options import check_options

        check_options(None, self, "guided.", memory=False)

    def resolved(self, model) -> GuidedOptions:
        """These options with every None filled from :data:`FAMILY_DEFAULTS` for ``model``'s class."""
        family = FAMILY_DEFAULTS.get(type(model).__name__, FAMILY_DEFAULTS["other"])
        return dataclasses.replace(self, **{k: v for k, v in family.items() if getattr(self, k) is None})


FAMILY_DEFAULTS: dict[str, dict] = {
    "GPNR": {"band_samples": 8, "guard_samples": 4, "band": 0.03},
    "IBRNet": {"band_samples": 16, "guard_samples": 8, "band": 0.06},
    "OmniRecon": {"band_samples": 8, "guard_samples": 4, "band": 0.01},
    "other": {"band_samples": 16, "guard_samples": 8, "band": 0.03},
}
"""Band and guard per model class, chosen on the shipped tiny checkpoints: candidates from the sweep rows of ``python
-m bench guided`` (fern at 336x252 and the procedural forward scene at 504x378; BENCHMARKS "Surface-guided volumetric
rendering"), then held to the 256-px protocol rows (``python -m bench quality --protocol-set cpu256 --guided``, 5 real
scenes, their protocol and extrapolation targets). IBRNet's ray transformer needs its 16 + 8 samples (fewer lost far
more than the band saves); a band of 0.06 instead of 0.03 came closer to the full render on both sweep scenes and
raised most of the protocol rows. GPNR with 6 + 2 in 0.06 (less CPU) and Omni-Recon with 8 + 4 in 0.03 (closer to the
full render on the procedural scene, whose surface a narrow band around the low-resolution prior misses) each lowered
the protocol rows (lego most), so both keep these values. Off by default: against the full render it costs more
than the issue's tolerance on the procedural scene."""


def to_unit(z: Tensor, near: float, far: float, inverse: bool) -> Tensor:
    """z-depth -> the sampling parameter in ``[0, 1]`` over ``[near, far]`` (inverse depth when ``inverse``)."""
    if inverse:
        return (1.0 / near - 1.0 / z) / (1.0 / near - 1.0 / far)
    return (z - near) / (far - near)


def from_unit(u: Tensor, near: float, far: float, inverse: bool) -> Tensor:
    """The inverse of :func:`to_unit`: ``u`` in ``[0, 1]`` -> z-depth."""
    if inverse:
        return 1.0 / (1.0 / near * (1 - u) + 1.0 / far * u)
    return near * (1 - u) + far * u


def prior_from_outputs(out: dict[str, Tensor], min_opacity: float) -> Tensor:
    """The z-depth prior of a ``render_view`` output ``# [h, w]``: ``depth`` (divided by the opacity ``acc`` where
    the model reports it: their depth is not normalised), NaN where the output is not ``valid`` or ``acc`` is
    below ``min_opacity``."""
    depth = out["depth"].float()
    trust = out["valid"].bool() if "valid" in out else torch.ones_like(depth, dtype=torch.bool)
    if "acc" in out:
        acc = out["acc"].float()
        depth = depth / acc.clamp_min(1e-6)
        trust = trust & (acc >= min_opacity)
    return torch.where(trust, depth, torch.full_like(depth, float("nan")))


def pixel_bands(prior: Tensor, height: int, width: int, near: float, far: float, inverse: bool,
                options: GuidedOptions) -> tuple[Tensor, Tensor]:
    """Per-pixel band ``[lo, hi]`` of a target of ``height x width`` in the sampling parameter, from a z-depth
    ``prior # [h, w]`` (NaN: none; any size): the min and max of the 2x2 prior cells around the pixel's centre
    (those bilinear upsampling would blend), widened by ``options.band`` and clipped to ``[0, 1]``. NaN where one
    of them is untrusted or they spread wider than ``options.max_spread``. ``# [H, W]`` each."""
    u = to_unit(prior.float(), near, far, inverse).clamp(0, 1)  # [h, w]
    h, w = u.shape
    y = (torch.arange(height) + 0.5) * h / height - 0.5  # pixel centres in prior cells
    x = (torch.arange(width) + 0.5) * w / width - 0.5
    rows = [y.floor().long().clamp(0, h - 1), (y.floor().long() + 1).clamp(0, h - 1)]  # [H] each
    cols = [x.floor().long().clamp(0, w - 1), (x.floor().long() + 1).clamp(0, w - 1)]  # [W] each
    corners = torch.stack([u[r][:, c] for r in rows for c in cols])  # [4, H, W]
    bad = torch.isnan(corners).any(0)
    lo = torch.where(torch.isnan(corners), 2.0, corners).amin(0)
    hi = torch.where(torch.isnan(corners), -1.0, corners).amax(0)
    drop = bad | (hi - lo > options.max_spread)
    nan = torch.full_like(lo, float("nan"))
    return (torch.where(drop, nan, (lo - options.band).clamp(0, 1)),
            torch.where(drop, nan, (hi + options.band).clamp(0, 1)))


def band_depths(lo: Tensor, hi: Tensor, near: float, far: float, inverse: bool, options: GuidedOptions) -> Tensor:
    """Sample z-depths of rays with band ``[lo, hi] # [R]`` (sampling parameter): ``band_samples`` evenly over the
    band and ``guard_samples`` at the cell centres of the whole range, sorted. ``# [R, band + guard]``"""
    n, g = options.band_samples, options.guard_samples
    t = torch.linspace(0.0, 1.0, n, dtype=lo.dtype, device=lo.device)  # [n]
    u = lo[:, None] + (hi - lo)[:, None] * t  # [R, n]
    if g > 0:
        guard = ((torch.arange(g, dtype=lo.dtype, device=lo.device) + 0.5) / g).expand(len(lo), g)  # [R, g]
        u = torch.cat([u, guard], -1)
    return from_unit(u.sort(-1).values, near, far, inverse)


def render_guided(model, features, camera: Cameras, options: GuidedOptions, chunk: int = 4096,
                  prior: Tensor | None = None, **render_kw) -> dict[str, Tensor]:
    """``model.render_view(features, camera, chunk, **render_kw)`` with surface-guided sampling (``options.on``):
    per-pixel outputs ``# [H, W, ...]`` that the guided and the full path share, plus ``guided # [H, W]`` (the
    pixel was rendered in a band). ``prior # [h, w]``: a z-depth map of the view (NaN: no prior; any size); None:
    the model's own render at ``1 / options.prior_scale`` size. Off (or a model without ``capabilities.guided``):
    ``render_view`` itself, with ``guided`` all False."""
    if not options.on or not model.capabilities.guided:
        out = model.render_view(features, camera, chunk, **render_kw)
        return {**out, "guided": torch.zeros(camera.height, camera.width, dtype=torch.bool)}
    src = features.sources
    inverse = src.rig == "forward"
    options = options.resolved(model)
    if prior is None:
        small = camera.rescaled(1.0 / options.prior_scale)
        prior = prior_from_outputs(model.render_view(features, small, chunk, **render_kw), options.min_opacity)
    H, W = camera.height, camera.width
    lo, hi = pixel_bands(prior.cpu(), H, W, src.near, src.far, inverse, options)
    has = ~torch.isnan(lo).flatten()  # [H W]
    parts = {}
    pixels = has.nonzero()[:, 0]
    if len(pixels):
        z = band_depths(lo.flatten()[pixels], hi.flatten()[pixels], src.near, src.far, inverse, options)
        out = model.render_view(features, camera, chunk, pixels=pixels, depths=z.to(src.images), **render_kw)
        missed = out["acc"].cpu() < options.min_opacity if "acc" in out else torch.zeros(len(pixels), dtype=torch.bool)
        has[pixels[missed]] = False  # the band found no surface: the full path there
        parts[True] = (pixels[~missed], {k: v[~missed.to(v.device)] for k, v in out.items()})
    pixels = (~has).nonzero()[:, 0]
    if len(pixels):
        parts[False] = (pixels, model.render_view(features, camera, chunk, pixels=pixels, **render_kw))
    return _scatter(parts, H, W)


def _scatter(parts: dict[bool, tuple[Tensor, dict[str, Tensor]]], height: int, width: int) -> dict[str, Tensor]:
    """Per-pixel outputs of the guided and full parts (``{guided: (pixels # [M], outputs # [M, ...])}``) into
    full images ``# [H, W, ...]``; only the keys every part has with the same per-ray shape (not e.g. GPNR's
    per-sample ``alpha``, whose sample count differs)."""
    keys = {k for k in set.intersection(*(set(o) for _, o in parts.values()))
            if len({o[k].shape[1:] for _, o in parts.values()}) == 1}
    out = {}
    for k in sorted(keys):
        first = next(iter(parts.values()))[1][k]
        buf = first.new_zeros(height * width, *first.shape[1:])
        for pixels, o in parts.values():
            buf[pixels.to(buf.device)] = o[k]
        out[k] = buf.reshape(height, width, *first.shape[1:])
    guided = torch.zeros(height * width, dtype=torch.bool)
    if True in parts:
        guided[parts[True][0]] = True
    out["guided"] = guided.reshape(height, width)
    return out
