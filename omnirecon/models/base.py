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
from omnirecon.models.fast import FAST, rendering
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
        (graph kept: the training forward). Every model renders each ray independently, so the outputs and
        their gradients are those of one call up to float rounding; small per-sample tensors stay in cache
        (reference, ``train_batch = 0``: one call)."""
        n, b = len(rays), FAST.train_batch
        if b <= 0 or n <= b:
            return self.render_rays(features, rays, **kwargs)
        parts = [self.render_rays(features, rays[s:s + b], **kwargs) for s in range(0, n, b)]
        sizes = [min(b, n - s) for s in range(0, n, b)]
        return {k: torch.cat([p[k] for p in parts]) if all(p[k].dim() >= 1 and p[k].shape[0] == m
                                                          for p, m in zip(parts, sizes)) else v
                for k, v in parts[0].items()}

    def render_view(self, features, camera: Cameras, chunk: int = 4096, signals: Tensor | None = None
                    ) -> dict[str, Tensor]:
        """Render one full image in chunks of ``chunk`` rays; outputs reshaped to ``[H, W, ...]``.

        ``signals # [V, H, W, C]`` (per-source-view 2-D maps) is passed to ``render_rays`` when given
        (models that support lifting return ``signal # [H, W, C]``; see :mod:`omnirecon.lift`).
        ``camera`` may be in any float dtype and on any device (a :class:`~omnirecon.data.scene.Scene`'s
        cameras are float64): it is moved to the sources' dtype and device first.

        The fast paths of :mod:`omnirecon.models.fast` apply here (``inference_mode``, ``render_batch``,
        ``preallocate``, ``bf16_render``); floating outputs keep the sources' dtype."""
        src = getattr(features, "sources", None)
        if src is not None:
            camera = camera.to(device=src.images.device, dtype=src.images.dtype)
        rays = Rays.from_image(camera)
        extra = {} if signals is None else {"signals": signals}
        batch = min(chunk, FAST.render_batch) if FAST.render_batch > 0 else chunk
        h, w = camera.height, camera.width
        with torch.inference_mode() if FAST.inference_mode else torch.no_grad(), rendering():
            if not FAST.preallocate:  # the reference: a list of chunks, concatenated
                parts: dict[str, list[Tensor]] = {}
                for start in range(0, len(rays), batch):
                    out = self.render_rays(features, rays[start:start + batch], **extra)
                    for k, v in out.items():
                        if v.dim() >= 1 and v.shape[0] == min(batch, len(rays) - start):
                            parts.setdefault(k, []).append(v)
                return {k: torch.cat(v).reshape(h, w, *v[0].shape[1:]) for k, v in parts.items()}
            n, bufs = len(rays), None
            float_dtype = rays.origins.dtype
            for start in range(0, n, batch):
                m = min(batch, n - start)
                if FAST.compile and m < batch < n:  # pad the last batch: compiled graphs keep one shape
                    part = rays[torch.arange(start, start + batch, device=rays.origins.device).clamp_max(n - 1)]
                else:
                    part = rays[start:start + m]
                out = {k: v[:m] if v.dim() >= 1 and v.shape[0] == len(part) else v
                       for k, v in self.render_rays(features, part, **extra).items()}
                if bufs is None:  # one buffer per per-ray output, filled in place
                    bufs = {k: torch.empty((n, *v.shape[1:]), device=v.device,
                                           dtype=float_dtype if v.is_floating_point() else v.dtype)
                            for k, v in out.items() if v.dim() >= 1 and v.shape[0] == m}
                for k, buf in bufs.items():
                    buf[start:start + m] = out[k]
            return {k: v.reshape(h, w, *v.shape[1:]) for k, v in (bufs or {}).items()}
