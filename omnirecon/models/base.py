"""The contract every generalizable model follows (pixelSplat/nerfacc style).

``encode`` turns the source views into view-independent ``SourceFeatures`` once per scene;
``render_rays`` renders any batch of target rays from them; ``render_view`` renders a whole image
in chunks of bounded memory. Models never own the data pipeline or the renderer's sampling loop.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor, nn

from omnirecon.cameras import Cameras


@dataclass
class Sources:
    """The posed source views a model conditions on."""

    images: Tensor
    """Source RGB in [0, 1]. ``# [V, H, W, 3]``"""
    cameras: Cameras
    """Source cameras (``V``), OpenCV camera-to-world."""
    near: float
    """Near z-depth bound of the scene."""
    far: float
    """Far z-depth bound of the scene."""
    rig: str = "unknown"
    """``"forward"`` (forward-facing: models may sample in inverse depth), ``"object"`` or ``"unknown"``."""
    bounds: Tensor | None = None
    """Axis-aligned box holding the content, ``[min, max]`` (Omni-Recon's feature volume). ``# [2, 3]``"""

    def to(self, device) -> Sources:
        bounds = None if self.bounds is None else self.bounds.to(device)
        return Sources(self.images.to(device), self.cameras.to(device), self.near, self.far, self.rig, bounds)

    @staticmethod
    def from_scene(scene, indices) -> Sources:
        """Views ``indices`` of a :class:`~omnirecon.data.scene.Scene` as sources; near/far and bounds span
        the scene."""
        idx = torch.as_tensor(list(indices), dtype=torch.long)
        return Sources(scene.images[idx], scene.cameras[idx].to(dtype=scene.images.dtype),
                       float(scene.near.min()), float(scene.far.max()), scene.rig,
                       scene.bounds.to(dtype=scene.images.dtype))


@dataclass
class Rays:
    """A batch of target rays."""

    origins: Tensor
    """Ray origins (the target camera centre). ``# [R, 3]``"""
    directions: Tensor
    """Unit ray directions. ``# [R, 3]``"""
    up: Tensor
    """Target camera y axis in world, per ray (fixes the roll of GPNR's canonical frame). ``# [R, 3]``"""
    z_scale: Tensor
    """Cosine between each ray and its camera's optical axis: ``z_depth = distance * z_scale``. ``# [R]``"""

    def __len__(self) -> int:
        return self.origins.shape[0]

    def __getitem__(self, index) -> Rays:
        return Rays(*(getattr(self, f.name)[index] for f in fields(self)))

    def to(self, device) -> Rays:
        return Rays(*(getattr(self, f.name).to(device) for f in fields(self)))

    @staticmethod
    def from_pixels(cameras: Cameras, cam_index: Tensor, uv: Tensor) -> Rays:
        """Rays through pixels ``uv # [R, 2]`` of cameras ``cam_index # [R]``."""
        cams = cameras[cam_index]
        o, d = cams.rays(uv[:, None, :])  # [R, 1, 3]
        o, d = o[:, 0], d[:, 0]
        return Rays(o, d, cams.R[:, :, 1], (d * cams.forward).sum(-1))

    @staticmethod
    def from_image(camera: Cameras) -> Rays:
        """All pixel-centre rays of one camera, row-major (``R = H * W``)."""
        uv = camera.pixel_centers().reshape(-1, 2)
        return Rays.from_pixels(camera, torch.zeros(len(uv), dtype=torch.long, device=uv.device), uv)


class GeneralizableModel(nn.Module):
    """Base class: subclasses implement ``encode`` and ``render_rays``."""

    def encode(self, sources: Sources):
        raise NotImplementedError

    def render_rays(self, features, rays: Rays) -> dict[str, Tensor]:
        """Render rays. Returns at least ``rgb # [R, 3]``; models add ``depth # [R]`` (z-depth),
        per-sample ``weights``, per-view ``blend`` weights and auxiliary outputs where they have them."""
        raise NotImplementedError

    @torch.no_grad()
    def render_view(self, features, camera: Cameras, chunk: int = 4096, signals: Tensor | None = None
                    ) -> dict[str, Tensor]:
        """Render one full image in chunks of ``chunk`` rays; outputs reshaped to ``[H, W, ...]``.

        ``signals # [V, H, W, C]`` (per-source-view 2-D maps) is passed to ``render_rays`` when given
        (models that support lifting return ``signal # [H, W, C]``; see :mod:`omnirecon.lift`).
        ``camera`` may be in any float dtype and on any device (a :class:`~omnirecon.data.scene.Scene`'s
        cameras are float64): it is moved to the sources' dtype and device first."""
        src = getattr(features, "sources", None)
        if src is not None:
            camera = camera.to(device=src.images.device, dtype=src.images.dtype)
        rays = Rays.from_image(camera)
        extra = {} if signals is None else {"signals": signals}
        parts: dict[str, list[Tensor]] = {}
        for start in range(0, len(rays), chunk):
            out = self.render_rays(features, rays[start:start + chunk], **extra)
            for k, v in out.items():
                if v.dim() >= 1 and v.shape[0] == min(chunk, len(rays) - start):
                    parts.setdefault(k, []).append(v)
        h, w = camera.height, camera.width
        return {k: torch.cat(v).reshape(h, w, *v[0].shape[1:]) for k, v in parts.items()}
