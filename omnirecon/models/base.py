"""The contract every generalizable model follows (pixelSplat/nerfacc style).

``encode`` turns the source views into view-independent ``SourceFeatures`` once per scene;
``render_rays`` renders any batch of target rays from them; ``render_view`` renders a whole image
in chunks of bounded memory. Models never own the data pipeline or the renderer's sampling loop.

What a model can do beyond colour is declared, not discovered: each class sets
:attr:`GeneralizableModel.capabilities` (:class:`Capabilities`), and callers (training, lifting, the
mesh path, export, benchmarks) read it instead of probing signatures or attributes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from omnirecon.cameras import Cameras
from omnirecon.models.fast import FAST, grad_mode, render_batches, render_sub_batches, rendering
from omnirecon.rays import Rays, Sources


@dataclass(frozen=True)
class Capabilities:
    """What a model renders besides ``rgb``; the keyword arguments its ``render_rays`` accepts follow."""

    depth: bool = False
    """``render_rays`` returns z-depth ``depth # [R]`` (meshing, depth metrics)."""
    signals: bool = False
    """``render_rays(features, rays, signals=...)`` blends per-source 2-D maps with the model's own
    per-view weights and returns ``signal`` (predict-then-blend lifting, editing)."""
    jitter: bool = False
    """``render_rays(features, rays, jitter=True)`` draws stratified samples (training)."""
    appearance: bool = False
    """An appearance branch that colours surface points alone: ``shade(features, points, origins)``
    and ``model.appearance`` (the real-time mesh path, export, fine-tuning, PET)."""
    passes: bool = False
    """Two passes, coarse then fine on importance samples (IBRNet, Omni-Recon): ``render_rays`` takes the
    output-changing options ``fine_pass: bool | None = None`` (False: outside training, render the coarse pass
    only, as a model without a fine pass would: depth maps for meshing, where the coarse depth of both
    shipped tiny models scored close to the fine depth at less than half the samples; None: the model's
    default, the fine pass unless its config says otherwise, e.g. Omni-Recon's ``render_fine_pass``) and
    ``surface_samples: int = 0`` (n > 0: outside training, the fine pass evaluates only n importance
    samples around the coarse surface instead of the coarse samples plus the fine ones; both shipped
    models lose much of their held-out PSNR with it). Both are quality/speed trades measured by
    ``bench/fast_paths.py``, not fast paths with a reference twin."""
    guided: bool = False
    """``render_rays(features, rays, depths=z)`` renders one pass (a two-pass model's final one) at the caller's
    sample z-depths ``z # [R, S]`` (increasing) instead of its own sampling: surface-guided rendering
    (:mod:`omnirecon.models.guided`)."""
    colour_weights: bool = False
    """``render_rays(features, rays, colour_weights=True)`` adds ``colour_weights # [R, S, K]`` and
    ``colour_depths # [R, S]`` where its ``rgb`` is a blend of the source colours: ``rgb = sum_{s, k}
    colour_weights[s, k] * c_k(x_s)``, ``c_k`` source ``k``'s image sampled bilinearly (border padding) where the
    point at z-depth ``colour_depths[s]`` on the ray lands, ``K`` every given source (zero weight for one the model
    left out). A model whose ``rgb`` is not such a blend (GPNR's feature head) leaves both keys out. Upsampled
    guided rendering (:func:`omnirecon.models.guided.render_upsampled`) reads them."""


class GeneralizableModel(nn.Module):
    """Base class: subclasses implement ``encode`` and ``render_rays`` and declare ``capabilities``."""

    capabilities = Capabilities()
    """What the model renders besides colour (class attribute)."""

    def encode(self, sources: Sources):
        raise NotImplementedError

    def render_rays(self, features, rays: Rays) -> dict[str, Tensor]:
        """Render rays. Returns at least ``rgb # [R, 3]``; models add ``depth # [R]`` (z-depth),
        per-sample ``weights``, per-view ``blend`` weights and auxiliary outputs where they have them."""
        raise NotImplementedError

    def render_rays_batched(self, features, rays: Rays, **kwargs) -> dict[str, Tensor]:
        """``render_rays`` on sub-batches of at most ``FAST.train_batch`` rays, per-ray outputs concatenated
        (graph kept: the training forward; :func:`omnirecon.models.fast.render_sub_batches`)."""
        return render_sub_batches(lambda r: self.render_rays(features, r, **kwargs), rays, FAST.train_batch)

    def render_view(self, features, camera: Cameras, chunk: int = 4096, signals: Tensor | None = None,
                    fine_pass: bool | None = None, surface_samples: int = 0, pixels: Tensor | None = None,
                    depths: Tensor | None = None, colour_weights: bool = False) -> dict[str, Tensor]:
        """Render one full image in chunks of ``chunk`` rays; outputs reshaped to ``[H, W, ...]``.
        ``pixels # [M]`` (flat row-major indices): render only those pixels, outputs ``[M, ...]``
        (every model renders each ray on its own: the same values as the full image's at those pixels).

        ``signals # [V, H, W, C]`` (per-source-view 2-D maps) is passed to ``render_rays`` when given
        (models that support lifting return ``signal # [H, W, C]``; see :mod:`omnirecon.lift`).
        ``fine_pass`` and ``surface_samples`` are passed to the ``render_rays`` of two-pass models
        (``capabilities.passes``, where they are documented); a one-pass model renders its only pass
        whatever they say. ``depths # [N, S]`` (one row per rendered ray: per pixel, or per entry of ``pixels``;
        models with ``capabilities.guided``): every ray samples at its row's z-depths instead of the model's own
        (:mod:`omnirecon.models.guided`). ``colour_weights`` (models with ``capabilities.colour_weights``): add the
        outputs :attr:`Capabilities.colour_weights` names. ``camera`` may be in any float dtype and on any device (a
        :class:`~omnirecon.data.scene.Scene`'s cameras are float64): it is moved to the sources' dtype
        and device first.

        The fast paths of :mod:`omnirecon.models.fast` apply here (``inference_mode``, ``render_batch``,
        ``preallocate``, ``compile``, ``bf16_render``); floating outputs keep the sources' dtype."""
        src = getattr(features, "sources", None)
        if src is not None:
            camera = camera.to(device=src.images.device, dtype=src.images.dtype)
        rays = Rays.from_image(camera)
        height, width = camera.height, camera.width
        if pixels is not None:
            rays, height, width = rays[pixels.to(rays.origins.device)], 1, len(pixels)
        extra = {} if signals is None else {"signals": signals}
        if colour_weights:
            extra["colour_weights"] = True
        if self.capabilities.passes:
            extra.update(fine_pass=fine_pass, surface_samples=surface_samples)
        batch = min(chunk, FAST.render_batch) if FAST.render_batch > 0 else chunk
        render = (lambda r, start: self.render_rays(features, r, **extra)) if depths is None else \
            _with_depths(lambda r, z: self.render_rays(features, r, depths=z, **extra), depths)
        with grad_mode(), rendering():
            out = render_batches(render, rays, batch, height, width)
        return out if pixels is None else {k: v[0] for k, v in out.items()}


def _with_depths(render, depths: Tensor):
    """``render(rays, z)`` as the ``render(rays, start)`` of :func:`~omnirecon.models.fast.render_batches`, which
    calls it on slices of the rays starting at ``start`` (the last one padded with copies of the last ray when
    compiled; batches in any order, on several threads): each call gets the rows of ``depths # [N, S]`` of its
    slice."""
    def call(rays: Rays, start: int) -> dict[str, Tensor]:
        idx = torch.arange(start, start + len(rays), device=depths.device).clamp_max(len(depths) - 1)
        return render(rays, depths[idx])
    return call
