"""The data types every layer passes around: the posed source views a model conditions on
(:class:`Sources`) and a batch of target rays (:class:`Rays`). They sit below data, render and models,
which all use them; they hold tensors and cameras, never a network."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

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
    masks: Tensor | None = None
    """Object masks of the sources (True: the object; object captures such as DTU), ``None`` when the scene has
    none. The mesh path's angle blend down-weights a source whose pixel lies off its object
    (:func:`omnirecon.mesh.kernel.mask_falloff`). ``# [V, H, W]`` bool"""

    def to(self, device) -> Sources:
        bounds = None if self.bounds is None else self.bounds.to(device)
        masks = None if self.masks is None else self.masks.to(device)
        return Sources(self.images.to(device), self.cameras.to(device), self.near, self.far, self.rig, bounds, masks)

    def subset(self, keep: Tensor) -> Sources:
        """The sources ``keep # [k]`` (indices), in that order; near/far, rig and bounds as they are."""
        return Sources(self.images[keep], self.cameras[keep], self.near, self.far, self.rig, self.bounds,
                       None if self.masks is None else self.masks[keep])

    @staticmethod
    def from_scene(scene, indices) -> Sources:
        """Views ``indices`` of a :class:`~omnirecon.data.scene.Scene` as sources; near/far and bounds span
        the scene."""
        idx = torch.as_tensor(list(indices), dtype=torch.long)
        return Sources(scene.images[idx], scene.cameras[idx].to(dtype=scene.images.dtype),
                       float(scene.near.min()), float(scene.far.max()), scene.rig,
                       scene.bounds.to(dtype=scene.images.dtype),
                       None if scene.masks is None else scene.masks[idx].bool())


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

    def distances(self, z: Tensor) -> Tensor:
        """Distances from the origins of the points at z-depths ``z # [R, S]`` (or ``# [S]``, the same for
        every ray): ``z / z_scale``. ``# [R, S]``"""
        return z / self.z_scale.clamp_min(1e-6)[:, None]

    def points(self, z: Tensor, unit_z: bool = False) -> Tensor:
        """World points at z-depths ``z # [R, S]`` (or ``# [S]``) along the rays: ``o + d (z / z_scale)``.
        ``# [R, S, 3]``

        ``unit_z``: the same points rounded the other way, ``o + (d / z_scale) z`` (directions scaled to unit
        z-depth), as the plane-sweep floor and IBRNet compute them. Their published numbers depend on that
        rounding: with the other one the floor's best depth plane flips on near-ties (dtu_scan24 at 50 px:
        depth off by one plane on some pixels, 18 more mesh vertices) and IBRNet's depth moves by 4e-5."""
        if unit_z:
            return self.origins[:, None] + (self.directions / self.z_scale[:, None].clamp_min(1e-6))[:, None] * z[..., None]
        return self.origins[:, None] + self.directions[:, None] * self.distances(z)[..., None]

    @staticmethod
    def from_pixels(cameras: Cameras, cam_index: Tensor, uv: Tensor) -> Rays:
        """Rays through pixels ``uv # [R, 2]`` of cameras ``cam_index # [R]``."""
        cams = cameras[cam_index]
        o, d = cams.rays(uv[:, None, :])  # [R, 1, 3]
        o, d = o[:, 0], d[:, 0]
        return Rays(o, d, cams.R[:, :, 1], (d * cams.forward).sum(-1))

    @staticmethod
    def from_image(camera: Cameras) -> Rays:
        """All pixel-centre rays of one camera (the first of ``camera``), row-major (``R = H * W``). The
        camera's centre and up axis are broadcast to every ray (views, not per-pixel copies)."""
        camera = camera[:1]
        o, d = camera.rays(camera.pixel_centers().reshape(1, -1, 2))  # [1, R, 3] each
        o, d = o[0], d[0]
        return Rays(o, d, camera.R[0, :, 1].expand_as(d), (d * camera.forward[0]).sum(-1))
