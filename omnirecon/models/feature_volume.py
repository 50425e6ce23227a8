"""Omni-Recon's feature volume (``shared/docs/omnirecon.md`` §2.2): three lattices over the volume box, each voxel
centre projected into every source view and the pyramid map sampled there, the masked mean and variance over views
per level, fused top-down by a 3-D decoder into ``V``. Part of :class:`omnirecon.models.omnirecon.OmniRecon` (the
state-dict keys stay the model's: ``volume.*``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from omnirecon.cameras import Cameras
from omnirecon.models.projector import project, sample
from omnirecon.rays import Sources

if TYPE_CHECKING:
    from omnirecon.models.omnirecon import OmniReconConfig


def volume_box(sources: Sources, mode: str, margin: float, forward: str = "content") -> Tensor:
    """The volume's ``[min, max]`` corners (``forward``: see :attr:`OmniReconConfig.forward_box`). ``# [2, 3]``"""
    dtype, device = sources.images.dtype, sources.images.device
    if mode == "unit" or sources.bounds is None:
        return torch.tensor([[-1.0] * 3, [1.0] * 3], dtype=dtype, device=device)
    lo, hi = sources.bounds.to(device=device, dtype=dtype)
    if forward == "cameras" and sources.rig == "forward":
        centres = sources.cameras.centers.to(device=device, dtype=dtype)  # [K, 3]
        lo, hi = torch.minimum(lo, centres.amin(0)), torch.maximum(hi, centres.amax(0))
    pad = margin * float((hi - lo).max()) / 2
    return torch.stack([lo - pad, hi + pad])


def lattice(box: Tensor, res: int) -> Tensor:
    """Voxel centres of a ``res^3`` lattice over ``box``, z-major so they reshape to ``[Z, Y, X]``. ``# [res^3, 3]``"""
    steps = (torch.arange(res, dtype=box.dtype, device=box.device) + 0.5) / res  # [res]
    axes = box[0][:, None] + steps[None] * (box[1] - box[0])[:, None]  # [3, res]
    zz, yy, xx = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return torch.stack([xx, yy, zz], -1).reshape(-1, 3)


def mean_var_volume(maps: Tensor, cameras: Cameras, points: Tensor, res: int) -> Tensor:
    """Masked mean and variance over views of ``maps # [V, C, h, w]`` at the voxel centres
    ``points # [res^3, 3]`` (invalid views: outside the image or behind the camera). ``# [1, 2C, res, res, res]``"""
    proj = project(cameras, points, maps.dtype)
    f = sample(maps, proj, "zeros")  # [V, C, P]
    m = proj.in_image.to(maps.dtype)[:, None]  # [V, 1, P]
    w = m / (m.sum(0, keepdim=True) + 1e-8)
    mean = (w * f).sum(0)  # [C, P]
    var = (w * (f - mean) ** 2).sum(0)
    return torch.cat([mean, var], 0).reshape(1, -1, res, res, res)


def _cbr3(cin: int, cout: int, running: bool) -> nn.Sequential:
    return nn.Sequential(nn.Conv3d(cin, cout, 3, padding=1, bias=False),
                         nn.BatchNorm3d(cout, track_running_stats=running), nn.ReLU())


def _tcbr3(cin: int, cout: int, running: bool) -> nn.Sequential:
    return nn.Sequential(nn.ConvTranspose3d(cin, cout, 3, stride=2, padding=1, output_padding=1, bias=False),
                         nn.BatchNorm3d(cout, track_running_stats=running), nn.ReLU())


class VolumeDecoder(nn.Module):
    """Top-down 3-D decoder (``VolumeRegularization_Multi_Res``): levels ``[L0, L1, L2]`` (fine to coarse) -> ``V``."""

    def __init__(self, cfg: OmniReconConfig):
        super().__init__()
        c0, c1, c2 = (2 * c for c in cfg.pyramid_channels)
        run = cfg.bn_running_stats
        self.a2, self.up1 = _cbr3(c2, c2, run), nn.Sequential(_cbr3(c2, c2, run), _tcbr3(c2, c1, run))
        self.a1, self.up0 = _cbr3(c1, c1, run), nn.Sequential(_cbr3(c1, c1, run), _tcbr3(c1, c0, run))
        self.a0, self.out = _cbr3(c0, c0, run), nn.Conv3d(c0, c0, 3, padding=1)

    def forward(self, levels: list[Tensor]) -> Tensor:
        l0, l1, l2 = levels
        u1 = self.up1(self.a2(l2))  # [1, c1, N/2, N/2, N/2]
        u0 = self.up0(u1 + self.a1(l1))  # [1, c0, N, N, N]
        return self.out(u0 + self.a0(l0))
