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

Upsampled rendering (``GuidedOptions.upsample``, :func:`render_upsampled`; ``Capabilities.colour_weights``): the
view is rendered (guided, or on the full path) at ``1 / upsample`` size, and each full-size pixel blends the
source photos at its own ray's points with the colour weights of its 4 nearest small cells, mixed bilinearly;
depth edges are rendered at full size.

Size: the options with their per-family defaults (a third of the module), the band and grid layouts, and the
upsampled path that reuses them are one sampling decision, kept together.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.models.projector import gather, project
from omnirecon.rays import Rays


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
    upsample: int | None = None
    """Blend at full size from a smaller render: the model renders the view at ``1 / upsample`` of its width and
    height (``upsample ** 2`` times fewer rays; ``small_path``); each pixel then blends the source colours at its own
    ray's points with the colour weights and sample depths of its 4 nearest small pixels, mixed bilinearly
    (:func:`render_upsampled`), and a pixel whose 2x2 small cells' depths spread wider than ``edge_spread`` is
    rendered by the model at full size (guided, the small render's depth its prior). 1: off. Models without
    ``capabilities.colour_weights``, or whose ``rgb`` is not a blend of the source colours, render at full size.
    None: the model family's value in :data:`FAMILY_DEFAULTS`."""
    small_path: Literal["guided", "full"] | None = None
    """With ``upsample``: how the small view is rendered: guided (its own prior at ``1 / prior_scale`` of the small
    size) or on the model's full path (every sample the checkpoint renders with, at ``1 / upsample ** 2`` of the
    rays: for weights whose full path takes many samples that a band does not replace). None: the model family's
    value in :data:`FAMILY_DEFAULTS`."""
    colour_samples: int | None = None
    """With ``upsample``: each small cell keeps this many of its samples, those with the most colour weight (its
    total weight kept), and each full-size pixel blends the colours of its 4 nearest cells' samples bilinearly. None:
    the model family's value in :data:`FAMILY_DEFAULTS`."""
    edge_spread: float = 0.2
    """With ``upsample``: a pixel whose 2x2 small-render cells (their depth divided by their opacity) spread wider
    than this fraction of the near-far range (sampling parameter) is rendered at full size. Smaller values render
    more pixels at full size: on the sweep scenes 0.05 and 0.1 came no closer to the full render than 0.2 (GPNR's
    depth on fern spreads widely between neighbours, and 0.05 rendered most of it at full size)."""

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
             "prior_scale": 4, "upsample": 2, "small_path": "guided", "colour_samples": 8},
    "IBRNet": {"layout": "band", "band_samples": 24, "guard_samples": 8, "band": 0.06, "grid_samples": 32,
               "prior_scale": 4, "upsample": 3, "small_path": "full", "colour_samples": 16},
    "OmniRecon": {"layout": "grid", "band_samples": 3, "guard_samples": 9, "band": 0.01, "grid_samples": 32,
                  "prior_scale": 8, "upsample": 2, "small_path": "guided", "colour_samples": 8},
    "other": {"layout": "band", "band_samples": 16, "guard_samples": 8, "band": 0.03, "grid_samples": 32,
              "prior_scale": 4, "upsample": 1, "small_path": "guided", "colour_samples": 8},
}
"""Layout, band, guard, prior size and upsampling per model class, chosen on the shipped tiny checkpoints:
candidates from the sweep rows of ``python -m bench guided`` (fern at 336x252 and the procedural forward scene at
504x378; BENCHMARKS "Surface-guided volumetric rendering"), then held to the 256-px protocol rows (``python -m bench
quality --protocol-set cpu256 --guided``, 5 real scenes, their protocol and extrapolation targets) against the full
path's. IBRNet's ray transformer needs many samples in a band (fewer lost far more than the band saves, and its
grid layout far more still); a band of 0.06 instead of 0.03 came closer to the full render on both sweep scenes and
raised most of the protocol rows; with the view rendered at half size, 24 band samples instead of 16 cost little and
came closer to the full render than 16 or 32. GPNR with 6 + 2 in 0.06 (less CPU), or on its grid, lowered the
procedural scene or the protocol rows, so it keeps these values. Omni-Recon's geometry transformer attends along
the ray: in a narrow band it drew another surface than its full path on the procedural scene, and with 5 or 6 guard
samples of its grid it tore a 256-px fox view into ghosts; with 9 guards and 3 band samples it stays closest to its
full path on the protocol rows for less CPU than the band layout, and a prior at 1/8 size costs a quarter of one at
1/4 and moves the rows by less than their spread. ``upsample`` 2 (the network at a quarter of the rays, the photos
blended at full size) cost GPNR and Omni-Recon no PSNR against their guided renders at full size on the sweep scenes
at a third of their time or less; 3 saved little more. ibrnet-tiny renders at 256 px and above with its 256-px
weights, whose full path takes 32 + 16 samples: every band layout tried (up to 32 + 16) drew the procedural scene
far below that full path, while its full path at a third of the size, blended at full size, stayed close to it on
both sweep scenes (``small_path`` ``full``, ``upsample`` 3; at half the size it took longer than the goal).
Mixing the 4 nearest cells bilinearly instead of taking the one a pixel lies in came closer to the full render on
every sweep row; of each cell's samples, the 8 strongest lost nothing against all of them for GPNR and Omni-Recon
(12 samples each) at less CPU, while IBRNet's 48 spread their weight wider and need more. Off by default: a render
option with its cost measured, not a bit-exact fast path."""


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
    ``render_view`` itself, with ``guided`` all False. With ``options.upsample > 1``: :func:`render_upsampled`."""
    if not options.on or not model.capabilities.guided:
        out = model.render_view(features, camera, chunk, **render_kw)
        return {**out, "guided": torch.zeros(camera.height, camera.width, dtype=torch.bool)}
    options = options.resolved(model)
    if options.upsample > 1 and model.capabilities.colour_weights and "signals" not in render_kw:
        return render_upsampled(model, features, camera, options, chunk, prior, **render_kw)
    if prior is None:
        prior = own_prior(model, features, camera, options, chunk, **render_kw)
    H, W = camera.height, camera.width
    return _scatter(_render_pixels(model, features, camera, options, prior, torch.arange(H * W), chunk, render_kw),
                    H, W)


def own_prior(model, features, camera: Cameras, options: GuidedOptions, chunk: int = 4096, **render_kw) -> Tensor:
    """The model's own z-depth prior of ``camera``'s view: its full-path render at ``1 / options.prior_scale`` size
    (:func:`prior_from_outputs`; resolved ``options``). ``# [h, w]``"""
    small = camera.rescaled(1.0 / options.prior_scale)
    # the grid layout's guard samples span the whole ray, so a pixel few sources see (not ``valid``) is guided too
    return prior_from_outputs(model.render_view(features, small, chunk, **render_kw), options.min_opacity,
                              use_valid=options.layout != "grid")


def _render_pixels(model, features, camera: Cameras, options: GuidedOptions, prior: Tensor, pixels: Tensor,
                   chunk: int, render_kw: dict) -> dict[bool, tuple[Tensor, dict[str, Tensor]]]:
    """The ``pixels # [M]`` (flat indices) of ``camera``'s view, guided by ``prior`` where it gives them a band and
    by the full path elsewhere (and where the band found no surface): ``{guided: (pixels, outputs)}`` for
    :func:`_scatter` (resolved ``options``)."""
    src = features.sources
    inverse = src.rig == "forward"
    H, W = camera.height, camera.width
    lo, hi = pixel_bands(prior.cpu(), H, W, src.near, src.far, inverse, options)
    lo, hi = lo.flatten()[pixels], hi.flatten()[pixels]
    has = ~torch.isnan(lo)  # [M]
    parts = {}
    if has.any():
        z = band_depths(lo[has], hi[has], src.near, src.far, inverse, options)
        out = model.render_view(features, camera, chunk, pixels=pixels[has], depths=z.to(src.images), **render_kw)
        missed = out["acc"].cpu() < options.min_opacity if "acc" in out else torch.zeros(len(z), dtype=torch.bool)
        parts[True] = (pixels[has][~missed], {k: v[~missed.to(v.device)] for k, v in out.items()})
        has[has.clone()] = ~missed  # the band found no surface: the full path there
    if (~has).any():
        parts[False] = (pixels[~has], model.render_view(features, camera, chunk, pixels=pixels[~has], **render_kw))
    return parts


def render_upsampled(model, features, camera: Cameras, options: GuidedOptions, chunk: int = 4096,
                     prior: Tensor | None = None, **render_kw) -> dict[str, Tensor]:
    """Surface-guided rendering at ``1 / options.upsample`` size, blended at full size (resolved ``options``; the
    model has ``capabilities.colour_weights``). The small view is rendered by :func:`render_guided` (``prior``, if
    given, guides it) or, with ``options.small_path == "full"``, by the model's full path. Each full-size pixel takes
    the small render's outputs at the cell it lies in; its ``rgb`` is the bilinear mix, over the 4 cells nearest it
    (:func:`bilinear_cells`), of the source colours at its own ray's points blended with each cell's
    ``colour_weights`` at its ``colour_depths`` (the ``options.colour_samples`` strongest: :func:`strongest_samples`;
    :func:`blend_sources`): the network's weights at the small size, the photos' detail at the full one. Pixels
    whose 2x2 cells spread wider than ``options.edge_spread`` in depth (edges, where a cell's weights belong to
    another surface) are rendered at full size, guided by the small render's depth. Outputs as
    :func:`render_guided`'s plus ``upsampled # [H, W]`` (the pixel was blended from the small render). A model whose
    ``rgb`` is not a blend (no ``colour_weights`` returned) is rendered guided at full size."""
    flat = dataclasses.replace(options, upsample=1)
    small = camera.rescaled(1.0 / options.upsample)
    if options.small_path == "full":
        low = {**model.render_view(features, small, chunk, colour_weights=True, **render_kw),
               "guided": torch.zeros(small.height, small.width, dtype=torch.bool)}
    else:
        low = render_guided(model, features, small, flat, chunk, prior, colour_weights=True, **render_kw)
    if "colour_weights" not in low:
        return render_guided(model, features, camera, flat, chunk, prior, **render_kw)
    src = features.sources
    inverse = src.rig == "forward"
    H, W, h, w = camera.height, camera.width, small.height, small.width
    y = ((torch.arange(H) + 0.5) * h / H).floor().long().clamp(0, h - 1)
    x = ((torch.arange(W) + 0.5) * w / W).floor().long().clamp(0, w - 1)
    cell = (y[:, None] * w + x[None]).flatten()  # [H W] the small pixel each pixel lies in
    spread = dataclasses.replace(flat, band=0.0, max_spread=options.edge_spread)
    edge = torch.isnan(pixel_bands(prior_from_outputs(low, 0.0, use_valid=False).cpu(), H, W, src.near, src.far,
                                   inverse, spread)[0]).flatten()  # [H W]
    weights = low.pop("colour_weights")
    depths, weights = strongest_samples(low.pop("colour_depths").reshape(h * w, -1),
                                        weights.reshape(h * w, *weights.shape[2:]), options.colour_samples)
    out = {k: v.reshape(h * w, *v.shape[2:])[cell.to(v.device)] for k, v in low.items()
           if v.dim() <= 3}  # [H W, ...] each: per-pixel outputs (not per-sample ones)
    rays = Rays.from_image(camera.to(device=src.images.device, dtype=src.images.dtype))
    corners, share = bilinear_cells(H, W, h, w)  # [4, H W], [4, H W]
    corners, share = corners.to(weights.device), share.to(weights.device)
    out["rgb"] = torch.zeros_like(out["rgb"])
    for i in range(0, H * W, chunk):
        part = slice(i, min(i + chunk, H * W))
        for c in range(4):  # the colours blended with each of the 4 cells' weights, bilinearly
            at = corners[c, part]
            out["rgb"][part] += share[c, part, None] * blend_sources(src, rays[part], depths[at], weights[at]).to(
                out["rgb"].dtype)
    out["upsampled"] = ~edge
    pixels = edge.nonzero()[:, 0]
    if len(pixels):
        trusted = prior_from_outputs(low, options.min_opacity, use_valid=options.layout != "grid")
        full = _scatter(_render_pixels(model, features, camera, flat, trusted, pixels, chunk, render_kw), H, W)
        for k in out:
            if k in full:
                v = full[k].reshape(H * W, *full[k].shape[2:])
                out[k][pixels.to(v.device)] = v[pixels.to(v.device)].to(out[k].dtype)
    return {k: v.reshape(H, W, *v.shape[1:]) for k, v in out.items()}


def bilinear_cells(height: int, width: int, h: int, w: int) -> tuple[Tensor, Tensor]:
    """For each pixel of a ``height x width`` image, the 4 cells of an ``h x w`` one that bilinear upsampling blends
    (flat indices, ``# [4, height width]``) and their shares (``# [4, height width]``, summing to 1; pixel centres
    aligned, borders clamped)."""
    def axis(n: int, m: int) -> tuple[Tensor, Tensor, Tensor]:
        u = ((torch.arange(n) + 0.5) * m / n - 0.5).clamp(0, m - 1)  # [n] in cell units
        lo = u.floor().long()
        return lo, (lo + 1).clamp_max(m - 1), u - lo
    y0, y1, fy = axis(height, h)
    x0, x1, fx = axis(width, w)
    cells = torch.stack([(a[:, None] * w + b[None]).flatten() for a in (y0, y1) for b in (x0, x1)])
    share = torch.stack([(p[:, None] * q[None]).flatten() for p in (1 - fy, fy) for q in (1 - fx, fx)])
    return cells, share


def strongest_samples(depths: Tensor, weights: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """Per row, the ``count`` samples of ``depths # [N, S]`` and ``weights # [N, S, K]`` with the most weight
    (summed over ``K``), the kept weights scaled so that each row's total stays the same; all of them when ``S <=
    count``. ``# [N, min(S, count)]``, ``# [N, min(S, count), K]``"""
    if depths.shape[1] <= count:
        return depths, weights
    mass = weights.sum(-1)  # [N, S]
    keep = mass.topk(count, -1).indices.sort(-1).values  # [N, count]
    kept = weights.gather(1, keep[..., None].expand(-1, -1, weights.shape[2]))  # [N, count, K]
    scale = mass.sum(-1) / kept.sum((1, 2)).clamp_min(1e-12)  # [N]
    return depths.gather(1, keep), kept * scale[:, None, None]


def blend_sources(sources, rays: Rays, depths: Tensor, weights: Tensor) -> Tensor:
    """``sum_{s, k} weights[r, s, k] * c_k(x_rs)``: the source images ``c_k`` sampled bilinearly (border padding)
    where the points ``x_rs`` of ``rays # [R]`` at z-depths ``depths # [R, S]`` land, blended with ``weights # [R,
    S, K]`` (a model's ``colour_weights``). ``# [R, 3]``"""
    proj = project(sources.cameras, rays.points(depths.to(rays.origins.dtype)), sources.images.dtype)
    colours = gather(sources.images.permute(0, 3, 1, 2), proj, "border")  # [R, S, K, 3]
    return (weights.to(colours.dtype)[..., None] * colours).sum((1, 2))


def _scatter(parts: dict[bool, tuple[Tensor, dict[str, Tensor]]], height: int, width: int) -> dict[str, Tensor]:
    """Per-pixel outputs of the guided and full parts (``{guided: (pixels # [M], outputs # [M, ...])}``) into
    full images ``# [H, W, ...]`` (zero at pixels no part has); only the keys every part has with the same per-ray
    shape (not e.g. GPNR's per-sample ``alpha``, whose sample count differs), besides ``colour_weights`` and
    ``colour_depths``, padded to the most samples (zero weight; the last depth repeated)."""
    parts = {g: (px, _pad_colour(o, max((p["colour_depths"].shape[1] for _, p in parts.values()
                                        if "colour_depths" in p), default=0)))
             for g, (px, o) in parts.items()}
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


def _pad_colour(out: dict[str, Tensor], samples: int) -> dict[str, Tensor]:
    """``out`` with ``colour_weights # [M, S, K]`` and ``colour_depths # [M, S]`` padded to ``samples`` (zero
    weights, the last depth repeated), so that parts rendered with different sample counts scatter together."""
    if "colour_depths" not in out or out["colour_depths"].shape[1] >= samples:
        return out
    z, wt = out["colour_depths"], out["colour_weights"]
    n = samples - z.shape[1]
    return {**out, "colour_depths": torch.cat([z, z[:, -1:].expand(-1, n)], 1),
            "colour_weights": torch.cat([wt, wt.new_zeros(wt.shape[0], n, wt.shape[2])], 1)}
