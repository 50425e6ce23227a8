"""Surface-guided volumetric rendering: each ray samples a narrow band around a depth prior plus a few guard
samples instead of marching the whole near-far range.

Two layouts (``GuidedOptions.layout``): ``band`` spreads the band's samples evenly over it; ``grid`` takes them from
the full path's own sample grid (the grid points nearest the prior, besides guards spread over the whole ray), so a
model that attends along its ray (Omni-Recon) sees the spacing and the context it renders with.

The prior is a z-depth map of the target view: given by the caller (a mesh rendered to depth, stereo depth) or,
by default, the model's own render at ``1 / prior_scale`` of the target's size, upsampled. A pixel's band spans the
prior depths of the 2x2 low-resolution cells around its centre (those bilinear upsampling blends), widened by
``band`` on each side, so that a pixel on a depth edge gets the whole step between the two surfaces; a pixel
whose cells spread wider than ``max_spread``, or touches a cell the prior does not trust (no value, opacity below
``min_opacity``, or, in the band layout, the model's own ``valid`` False), has no prior and is rendered by the full
path. Its reference twin is the full path itself: :func:`render_guided` with ``GuidedOptions(on=False)`` is
``model.render_view``, and the pixels without a prior are ``render_view(pixels=...)``, the same values as the full
image's there (``tests/models/test_guided.py`` checks both, and holds the guided render to a stated PSNR of the full
one).

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
from typing import Literal

import torch
from torch import Tensor

from omnirecon.cameras import Cameras


@dataclass
class GuidedOptions:
    """Surface-guided rendering (off by default)."""

    on: bool = False
    """Render each ray with prior from ``band_samples + guard_samples`` samples around its prior depth; rays
    without a prior (or with one the prior does not trust) take the full path. Off: the full path everywhere."""
    prior_scale: int | None = None
    """Without a given prior, the model renders the view at ``1 / prior_scale`` of its width and height with its
    full path (``prior_scale ** 2`` times fewer rays) and its depth, upsampled, is the prior. None: the model
    family's value in :data:`FAMILY_DEFAULTS`."""
    layout: Literal["band", "grid"] | None = None
    """Where a guided ray's samples go. ``band``: ``band_samples`` evenly over the band (the 2x2 prior cells'
    depths plus ``band`` on each side) and ``guard_samples`` at the centres of equal cells of the whole range.
    ``grid``: on the full path's own grid of ``grid_samples`` points (evenly over the range in the sampling
    parameter, both ends included): ``guard_samples`` grid points evenly over the whole ray, and the
    ``band_samples`` other grid points nearest the band's centre. A model that attends along its ray (Omni-Recon's
    geometry transformer) then sees the spacing it renders with and the whole ray as context. None: the model
    family's value in :data:`FAMILY_DEFAULTS`."""
    band_samples: int | None = None
    """Samples per ray around the prior (``layout``). None: the model family's value in :data:`FAMILY_DEFAULTS`."""
    guard_samples: int | None = None
    """Samples per ray over the whole near-far range, merged with the band's (``layout``): the model sees some of
    the space in front of and behind the band. None: the model family's value in :data:`FAMILY_DEFAULTS`."""
    grid_samples: int | None = None
    """The ``grid`` layout's points per ray over the whole range. None: the model's own full-path sample count
    (:func:`full_path_samples`) where it has one, else the family's value in :data:`FAMILY_DEFAULTS`."""
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
        family = dict(FAMILY_DEFAULTS.get(type(model).__name__, FAMILY_DEFAULTS["other"]))
        own = full_path_samples(model)
        if own:
            family["grid_samples"] = own
        out = dataclasses.replace(self, **{k: v for k, v in family.items() if getattr(self, k) is None})
        if out.layout == "grid" and out.band_samples + out.guard_samples > out.grid_samples:
            from omnirecon.errors import InputError

            raise InputError(f"--guided.band_samples + --guided.guard_samples ({out.band_samples} + "
                             f"{out.guard_samples}) exceed --guided.grid_samples ({out.grid_samples})", None,
                             "use fewer samples with --guided.layout grid, e.g. 3 + 9 of 32")
        return out


FAMILY_DEFAULTS: dict[str, dict] = {
    "GPNR": {"layout": "band", "band_samples": 8, "guard_samples": 4, "band": 0.03, "grid_samples": 32,
             "prior_scale": 4},
    "IBRNet": {"layout": "band", "band_samples": 16, "guard_samples": 8, "band": 0.06, "grid_samples": 32,
               "prior_scale": 4},
    "OmniRecon": {"layout": "grid", "band_samples": 3, "guard_samples": 9, "band": 0.01, "grid_samples": 32,
                  "prior_scale": 8},
    "other": {"layout": "band", "band_samples": 16, "guard_samples": 8, "band": 0.03, "grid_samples": 32,
              "prior_scale": 4},
}
"""Layout, band, guard and prior size per model class, chosen on the shipped tiny checkpoints: candidates from the
sweep rows of ``python -m bench guided`` (fern at 336x252 and the procedural forward scene at 504x378; BENCHMARKS
"Surface-guided volumetric rendering"), then held to the 256-px protocol rows (``python -m bench quality
--protocol-set cpu256 --guided``, 5 real scenes, their protocol and extrapolation targets) against the full path's.
IBRNet's ray transformer needs its 16 + 8 samples in a band (fewer lost far more than the band saves, and its grid
layout far more still); a band of 0.06 instead of 0.03 came closer to the full render on both sweep scenes and raised
most of the protocol rows. GPNR with 6 + 2 in 0.06 (less CPU), or on its grid, lowered the procedural scene or the
protocol rows, so it keeps these values. Omni-Recon's geometry transformer attends along the ray: in a narrow band it
drew another surface than its full path on the procedural scene, and with 5 or 6 guard samples of its grid it tore a
256-px fox view into ghosts; with 9 guards and 3 band samples it stays closest to its full path on the
protocol rows for less CPU than the band layout, and a prior at 1/8 size costs a quarter of one at 1/4 and moves the
rows by less than their spread. Off by default: a render option with its cost measured, not a bit-exact fast path."""


def full_path_samples(model) -> int | None:
    """The samples per ray of ``model``'s full path outside training (its first pass: GPNR's ``render_samples``,
    IBRNet's ``render_coarse_samples``, or the config's ``num_samples`` / ``coarse_samples``); None if it has none."""
    cfg = getattr(model, "cfg", None)
    for key in ("render_samples", "render_coarse_samples", "coarse_samples", "num_samples"):
        if getattr(cfg, key, None):
            return int(getattr(cfg, key))
    return None


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


def prior_from_outputs(out: dict[str, Tensor], min_opacity: float, use_valid: bool = True) -> Tensor:
    """The z-depth prior of a ``render_view`` output ``# [h, w]``: ``depth`` (divided by the opacity ``acc`` where
    the model reports it: their depth is not normalised), NaN where ``acc`` is below ``min_opacity`` or (with
    ``use_valid``) the output is not ``valid``."""
    depth = out["depth"].float()
    trust = out["valid"].bool() if use_valid and "valid" in out else torch.ones_like(depth, dtype=torch.bool)
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
    """Sample z-depths of rays with band ``[lo, hi] # [R]`` (sampling parameter), sorted, ``# [R, band + guard]``:
    ``band`` layout: ``band_samples`` evenly over the band and ``guard_samples`` at the cell centres of the whole
    range; ``grid`` layout: :func:`grid_units`."""
    n, g = options.band_samples, options.guard_samples
    if options.layout == "grid":
        return from_unit(grid_units((lo + hi) / 2, options.grid_samples, n, g), near, far, inverse)
    t = torch.linspace(0.0, 1.0, n, dtype=lo.dtype, device=lo.device)  # [n]
    u = lo[:, None] + (hi - lo)[:, None] * t  # [R, n]
    if g > 0:
        guard = ((torch.arange(g, dtype=lo.dtype, device=lo.device) + 0.5) / g).expand(len(lo), g)  # [R, g]
        u = torch.cat([u, guard], -1)
    return from_unit(u.sort(-1).values, near, far, inverse)


def grid_units(centre: Tensor, grid: int, band: int, guard: int) -> Tensor:
    """The ``grid`` layout in the sampling parameter, sorted, ``# [R, band + guard]``: of the ``grid`` points
    ``i / (grid - 1)``, the ``guard`` ones nearest ``linspace(0, 1, guard)`` (the whole ray, both ends) and the
    ``band`` other points nearest each ray's ``centre # [R]``. No point twice (``band + guard <= grid``:
    :meth:`GuidedOptions.resolved` checks it)."""
    idx = torch.arange(grid, device=centre.device)  # [N]
    base = torch.linspace(0, grid - 1, guard, device=centre.device).round().long().unique() if guard > 1 else \
        idx[:guard]  # [G]
    rest = idx[~torch.isin(idx, base)].to(centre.dtype)  # [N - G]
    near = (rest - centre[:, None] * (grid - 1)).abs().topk(band, -1, largest=False).indices  # [R, band]
    units = torch.cat([rest[near], base.to(centre.dtype).expand(len(centre), -1)], -1)  # [R, band + G]
    return units.sort(-1).values / (grid - 1)


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
        # the grid layout's guard samples span the whole ray, so a pixel few sources see (not ``valid``) is guided too
        prior = prior_from_outputs(model.render_view(features, small, chunk, **render_kw), options.min_opacity,
                                   use_valid=options.layout != "grid")
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
