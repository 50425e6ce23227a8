"""Training losses, in one place for every model: masked colour MSE, the depth L1 on both passes, the
mask loss (accumulated opacity against the object mask) on both passes, and the module that wraps a
model so DDP sees one forward. ``psnr`` converts an MSE for logs."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn


def masked_mse(pred: Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """Mean squared error over rays weighted by ``weight # [R]`` (0 where no weight, graph kept)."""
    err = (pred.float() - target.float()).square().mean(-1)  # [R]
    return (err * weight).sum() / weight.sum().clamp_min(1.0)


def masked_l1(pred: Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """Mean absolute error over rays ``# [R]`` weighted by ``weight # [R]`` (0 where no weight, graph kept)."""
    return ((pred.float() - target.float()).abs() * weight).sum() / weight.sum().clamp_min(1.0)


def depth_loss(out: dict[str, Tensor], depth: Tensor, valid: Tensor, near: float, far: float) -> Tensor:
    """L1 of the rendered z-depth (fine and coarse passes, where rendered) on valid rays whose
    ground-truth ``depth # [R]`` lies in ``[near, far]`` (0 = unknown)."""
    known = valid * ((depth >= near) & (depth <= far)).float()  # [R]
    loss = masked_l1(out["depth"], depth, known)
    if "depth_coarse" in out and out["depth_coarse"] is not out["depth"]:
        loss = loss + masked_l1(out["depth_coarse"], depth, known)
    return loss


def mask_loss(out: dict[str, Tensor], mask: Tensor, valid: Tensor) -> Tensor:
    """Squared error between the accumulated opacity ``acc # [R]`` (fine and coarse passes, where rendered)
    and the object mask ``mask # [R]`` (1 object, 0 empty) on valid rays: exactly 0 when the render is
    opaque on the mask and empty off it.

    The mask must mean *opaque vs empty*: right for scenes whose background is nothing (Blender objects,
    procedural scenes without ground). Where a real background or a ground surrounds the object, or the
    background colour is not black (models composite over black), it pulls against the colour loss."""
    loss = masked_mse(out["acc"][:, None], mask[:, None], valid)
    if "acc_coarse" in out and out["acc_coarse"] is not out["acc"]:
        loss = loss + masked_mse(out["acc_coarse"][:, None], mask[:, None], valid)
    return loss


class LossModule(nn.Module):
    """encode + render_rays + loss in one ``forward``, the module DDP wraps."""

    def __init__(self, model: nn.Module, aux_weight: float, depth_weight: float = 0.0, mask_weight: float = 0.0):
        super().__init__()
        self.model = model
        self.aux_weight = aux_weight
        self.depth_weight = depth_weight
        self.mask_weight = mask_weight
        self.jitter = model.capabilities.jitter  # IBRNet, Omni-Recon: stratified samples

    def forward(self, sources, rays, rgb: Tensor, depth: Tensor | None = None, mask: Tensor | None = None
                ) -> tuple[Tensor, Tensor, Tensor]:
        """-> loss, main-colour MSE (detached) and the fraction of valid rays. ``depth # [R]`` (0 = unknown)
        and ``mask # [R]`` (object mask) are the optional ground truths of the depth and mask losses."""
        out = self.model.render_rays_batched(self.model.encode(sources), rays,  # sub-batches: models/fast.py
                                             **({"jitter": True} if self.jitter else {}))
        valid = out["valid"].float() if "valid" in out else torch.ones_like(rgb[:, 0])  # [R]
        mse = masked_mse(out["rgb"], rgb, valid)
        loss = mse
        aux = out.get("rgb_aux", out.get("rgb_coarse"))
        if aux is not None and aux is not out["rgb"] and self.aux_weight > 0:
            loss = loss + self.aux_weight * masked_mse(aux, rgb, valid)
        if self.depth_weight > 0 and depth is not None and "depth" in out:
            loss = loss + self.depth_weight * depth_loss(out, depth, valid, sources.near, sources.far)
        if self.mask_weight > 0 and mask is not None and "acc" in out:
            loss = loss + self.mask_weight * mask_loss(out, mask.to(rgb.dtype), valid)
        return loss, mse.detach(), valid.mean().detach()


def psnr(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-10))
