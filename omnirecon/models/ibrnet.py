"""IBRNet (Wang et al., CVPR 2021), the baseline both seed papers beat.

Faithful to ``shared/docs/gpnr_ibrnet.md`` Part B: a residual U-Net gives per-view features;
each sample along a target ray gathers bilinearly sampled features and raw colours from every
source view plus the ``ray_diff`` direction code; mean/variance pooling with anti-alias weights,
two-step visibility, a density feature, a one-layer ray transformer over the samples, density
``sigma`` and colour as a softmax blend of the *source colours*; ``alpha = 1 - exp(-sigma)``
(no interval, as the reference). Coarse + fine passes (importance sampling from the coarse
weights). Departures: sampling at exact pixel centres (``align_corners=False`` with our +0.5
convention); the ray transformer masks *keys* of samples no view sees (the reference masks
query rows, see pitfall 13); the sample-index position code is computed for any sample count.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omnirecon.models.base import Capabilities, GeneralizableModel
from omnirecon.models.fast import FAST, compiled, concat_linear, is_rendering, net_autocast
from omnirecon.models.guided import to_unit
from omnirecon.models.pretrained import SingleMap
from omnirecon.models.projector import gather, project
from omnirecon.models.sampler import coarse_depths, fine_depths
from omnirecon.rays import Rays, Sources
from omnirecon.render.volume import alpha_from_density, composite, weights_from_alpha


@dataclass
class IBRNetConfig:
    """IBRNet hyper-parameters."""

    num_views: int = 10
    """Source views used per target."""
    coarse_samples: int = 64
    """Samples per ray of the coarse pass."""
    fine_samples: int = 64
    """Extra importance samples of the fine pass (0 disables the fine pass)."""
    channels: tuple[int, int, int] = (64, 128, 256)
    """Encoder widths of the three residual stages."""
    blocks: tuple[int, int, int] = (3, 4, 6)
    """Residual blocks per stage (ResNet34 layers 1-3)."""
    stem_stride: int = 2
    """Stride of the 7x7 stem: 2 gives features at 1/4 resolution (paper), 1 at 1/2."""
    feature_dim: int = 32
    """Feature channels per pass (the U-Net outputs twice this: coarse + fine halves)."""
    encoder: Literal["scratch", "vgg16", "alexnet"] = "scratch"
    """Image encoder: the residual U-Net trained from scratch, or a frozen pretrained backbone (HED's VGG16,
    ST-LPIPS's AlexNet) with a small trainable adapter to ``2 feature_dim`` channels at the U-Net's stride
    (:mod:`omnirecon.models.pretrained`)."""
    render_coarse_samples: int | None = None
    """Inside ``render_view`` (rendering outside training), the coarse pass's samples instead of
    ``coarse_samples``; None: ``coarse_samples``. Each rendered sample stands for the trained samples of its
    kind it replaces (coarse: ``coarse_samples / render_coarse_samples``; importance: ``fine_samples /
    render_fine_samples``): the ray transformer's index code counts in trained positions and its density is
    scaled by that number (IBRNet's alpha has no interval: it was learned for the trained spacing). Unscaled
    density scored lower on fox and lego. A render option measured per weights (``python -m bench
    tiny_levers``, ``python -m bench quality``)."""
    render_fine_samples: int | None = None
    """Inside ``render_view``, the fine pass's importance samples instead of ``fine_samples`` (added to the
    rendered coarse samples and rescaled as ``render_coarse_samples`` says). None: ``fine_samples``."""


PRESETS = {
    "ibrnet-paper": IBRNetConfig(),
    "ibrnet-tiny": IBRNetConfig(num_views=5, coarse_samples=32, fine_samples=16, channels=(16, 32, 64),
                                blocks=(1, 1, 1), stem_stride=1, feature_dim=16),
}


# ---------------------------------------------------------------------- feature network
class _Block(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, padding_mode="reflect", bias=False)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, padding_mode="reflect", bias=False)
        self.n1, self.n2 = nn.InstanceNorm2d(cout, affine=True), nn.InstanceNorm2d(cout, affine=True)
        self.skip = None if stride == 1 and cin == cout else nn.Sequential(
            nn.Conv2d(cin, cout, 1, stride, bias=False), nn.InstanceNorm2d(cout, affine=True))

    def forward(self, x: Tensor) -> Tensor:
        y = self.n2(self.conv2(F.relu(self.n1(self.conv1(x)))))
        return F.relu(y + (x if self.skip is None else self.skip(x)))


def _up_conv(cin: int, cout: int) -> nn.Module:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, 1, 1, padding_mode="reflect"), nn.InstanceNorm2d(cout, affine=True),
                         nn.ELU())


class ResUNet(nn.Module):
    """Residual encoder (stem + 3 stages) and a 2-step decoder back to the stage-1 resolution."""

    def __init__(self, cfg: IBRNetConfig):
        super().__init__()
        c1, c2, c3 = cfg.channels
        self.stem = nn.Sequential(nn.Conv2d(3, c1, 7, cfg.stem_stride, 3, padding_mode="reflect", bias=False),
                                  nn.InstanceNorm2d(c1, affine=True), nn.ReLU())

        def stage(cin, cout, n):
            return nn.Sequential(_Block(cin, cout, 2), *[_Block(cout, cout, 1) for _ in range(n - 1)])

        self.layer1, self.layer2, self.layer3 = stage(c1, c1, cfg.blocks[0]), stage(c1, c2, cfg.blocks[1]), \
            stage(c2, c3, cfg.blocks[2])
        self.up3, self.fuse2 = _up_conv(c3, c2), _up_conv(2 * c2, c2)
        self.up2, self.fuse1 = _up_conv(c2, c1), _up_conv(2 * c1, c1)
        self.out = nn.Conv2d(c1, 2 * cfg.feature_dim, 1)

    def forward(self, x: Tensor) -> Tensor:
        x1 = self.layer1(self.stem(x))
        x2 = self.layer2(x1)
        x3 = self.layer3(x2)
        y = self.up3(F.interpolate(x3, size=x2.shape[-2:], mode="bilinear", align_corners=False))
        y = self.fuse2(torch.cat([y, x2], 1))
        y = self.up2(F.interpolate(y, size=x1.shape[-2:], mode="bilinear", align_corners=False))
        y = self.fuse1(torch.cat([y, x1], 1))
        return self.out(y)


# ---------------------------------------------------------------------- per-sample aggregation
class _ELU(nn.ELU):
    """ELU that overwrites its input when ``FAST.inplace_elu`` (every use follows a Linear whose output
    nothing else reads)."""

    def forward(self, x: Tensor) -> Tensor:
        return F.elu(x, self.alpha, inplace=FAST.inplace_elu)


def _mlp(*dims: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(dims[:-1], dims[1:]):
        layers += [nn.Linear(a, b), _ELU()]
    return nn.Sequential(*layers[:-1])


def _weighted_stats(x: Tensor, w: Tensor) -> Tensor:
    """Weighted mean and variance over views: ``x # [..., V, C]``, ``w # [..., V, 1]`` -> ``# [..., 1, 2C]``."""
    mean = (x * w).sum(-2, keepdim=True)
    var = (w * (x - mean) ** 2).sum(-2, keepdim=True)
    return torch.cat([mean, var], -1)


def position_code(pos: Tensor, dim: int) -> Tensor:
    """Sinusoidal code of (possibly fractional) sample positions ``pos # [...]``. ``# [..., dim]``"""
    div = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32, device=pos.device) * (-math.log(10000.0) / dim))
    ang = pos.float()[..., None] * div
    code = torch.zeros(*pos.shape, dim, device=pos.device)
    code[..., 0::2], code[..., 1::2] = torch.sin(ang), torch.cos(ang)
    return code


def sample_index_code(num: int, dim: int, device=None) -> Tensor:
    """Sinusoidal position code of sample indices ``0..num-1``. ``# [num, dim]``"""
    return position_code(torch.arange(num, dtype=torch.float32, device=device), dim)


class Aggregator(nn.Module):
    """The "IBRNet MLP": multi-view features of each sample -> density and colour blend weights."""

    def __init__(self, feature_dim: int):
        super().__init__()
        c = feature_dim + 3
        self.dir_mlp = nn.Sequential(nn.Linear(4, 16), _ELU(), nn.Linear(16, c), _ELU())
        self.sharpness = nn.Parameter(torch.tensor(0.2))
        self.base = nn.Sequential(_mlp(3 * c, 64, 32), _ELU())
        self.vis = _mlp(32, 32, 33)
        self.vis2 = _mlp(32, 32, 1)
        self.density_feat = nn.Sequential(_mlp(65, 64, 16), _ELU())
        self.attn = nn.MultiheadAttention(16, 4, bias=False, batch_first=True)
        self.attn_norm = nn.LayerNorm(16)
        self.sigma = nn.Sequential(nn.Linear(16, 16), _ELU(), nn.Linear(16, 1), nn.ReLU())
        self.rgb = _mlp(37, 16, 8, 1)

    def forward(self, rgb_feat: Tensor, ray_diff: Tensor, mask: Tensor, stands_for: Tensor | None = None,
                positions: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``rgb_feat # [R, S, V, 3+C]``, ``ray_diff # [R, S, V, 4]``, ``mask # [R, S, V]`` ->
        ``sigma # [R, S]`` and view blend weights ``# [R, S, V]``. ``stands_for # [R, S]``: trained samples
        each rendered one stands for (the index code counts in trained positions); None: one each. ``positions # [R, S]``:
        the samples' positions in the trained sequence for the index code instead (surface-guided rendering)."""
        m = mask[..., None].to(rgb_feat.dtype)  # [R, S, V, 1]
        f = rgb_feat + self.dir_mlp(ray_diff)
        e = torch.exp(self.sharpness.abs() * (ray_diff[..., 3:] - 1))  # [R, S, V, 1]
        e_min = torch.where(m > 0, e, torch.full_like(e, math.inf)).amin(-2, keepdim=True)
        w = (e - torch.where(torch.isinf(e_min), torch.zeros_like(e_min), e_min)) * m
        w = w / (w.sum(-2, keepdim=True) + 1e-8)
        stats = _weighted_stats(f, w)  # [R, S, 1, 2C]
        first, act, second = self.base[0]  # the base MLP on [stats, f] (split_linear: the stats part once per sample)
        x = self.base[1](second(act(concat_linear(first, [stats, f]))))  # [R, S, V, 32]
        rv = F.elu(self.vis(x * w), inplace=FAST.inplace_elu)  # the reference's vis_fc ends with an ELU (32->32->33, ELU after both)
        r, v = rv[..., :32], torch.sigmoid(rv[..., 32:]) * m
        x = x + r
        v = torch.sigmoid(self.vis2(x * v)) * m  # [R, S, V, 1]
        vw = v / (v.sum(-2, keepdim=True) + 1e-8)
        dens = torch.cat([_weighted_stats(x, vw)[..., 0, :], vw.mean(-2)], -1)  # [R, S, 65] (reference: weight.mean)
        h = self.density_feat(dens)  # [R, S, 16]
        if positions is None:
            positions = None if stands_for is None else stands_for.cumsum(-1) - stands_for  # [R, S]
        code = sample_index_code(h.shape[1], 16, h.device) if positions is None else \
            position_code(positions, 16)  # [S, 16] or [R, S, 16]
        h = h + code.to(h.dtype)
        seen = mask.any(-1)  # [R, S]
        pad = ~seen & ~(~seen).all(-1, keepdim=True)
        if FAST.sdpa_attention:
            a = _ray_attention(self.attn, h, pad)
        else:
            a, _ = self.attn(h, h, h, key_padding_mask=pad, need_weights=False)
        h = self.attn_norm(h + a)
        sigma = self.sigma(h)[..., 0] * seen  # [R, S]
        logit = self.rgb[1:](concat_linear(self.rgb[0], [x, v, ray_diff]))[..., 0]  # the colour head on [x, v, ray_diff]
        logit = logit.masked_fill(~mask, -1e9)  # [R, S, V]
        return sigma, torch.softmax(logit, -1)


def _ray_attention(attn: nn.MultiheadAttention, h: Tensor, pad: Tensor) -> Tensor:
    """``attn(h, h, h, key_padding_mask=pad)`` (no biases, self-attention over samples) through
    ``scaled_dot_product_attention`` with a boolean mask. ``h # [R, S, E]``, ``pad # [R, S]`` -> ``# [R, S, E]``"""
    (R, S, E), heads = h.shape, attn.num_heads
    qkv = F.linear(h, attn.in_proj_weight).view(R, S, 3, heads, E // heads).permute(2, 0, 3, 1, 4)  # [3, R, H, S, D]
    o = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2], attn_mask=~pad[:, None, None, :])  # [R, H, S, D]
    return F.linear(o.transpose(1, 2).reshape(R, S, E), attn.out_proj.weight)


def trained_positions(z: Tensor, sources: Sources, coarse: int, fine: int) -> Tensor:
    """Where samples at z-depths ``z # [R, S]`` (increasing) would sit in the trained sequence of a pass over
    ``coarse`` uniform samples (in inverse depth on forward rigs) plus ``fine`` importance samples near the
    surface, for the ray transformer's index code: the coarse samples in front of each (its fraction of the
    near-far range) plus its share of the importance samples by rank. ``# [R, S]``"""
    u = to_unit(z, sources.near, sources.far, sources.rig == "forward")  # [R, S]
    rank = torch.arange(z.shape[1], dtype=z.dtype, device=z.device) / max(z.shape[1] - 1, 1)  # [S]
    return u.clamp(0, 1) * (coarse - 1) + rank * fine


# ---------------------------------------------------------------------- the model
@dataclass
class IBRNetFeatures:
    sources: Sources
    maps: Tensor
    """U-Net feature maps, coarse then fine halves. ``# [V, 2C, H', W']``"""


class IBRNet(GeneralizableModel):
    capabilities = Capabilities(depth=True, signals=True, jitter=True, passes=True, guided=True,
                                colour_weights=True)

    def __init__(self, cfg: IBRNetConfig):
        super().__init__()
        self.cfg = cfg
        self.unet = ResUNet(cfg) if cfg.encoder == "scratch" else \
            SingleMap(cfg.encoder, 2 * cfg.stem_stride, 2 * cfg.feature_dim, hidden=cfg.channels[0] * 2)
        self.coarse = Aggregator(cfg.feature_dim)
        self.fine = Aggregator(cfg.feature_dim) if cfg.fine_samples > 0 else None

    def encode(self, sources: Sources) -> IBRNetFeatures:
        return IBRNetFeatures(sources, self.unet(sources.images.permute(0, 3, 1, 2)))

    def _gather(self, feats: IBRNetFeatures, rays: Rays, z: Tensor, half: int, signals: Tensor | None = None):
        """Per-sample inputs at z-depths ``z # [R, S]``: rgb+features, ray_diff, valid mask; with
        ``signals # [V, H, W, C]`` also the per-view maps at each sample (sampled exactly as the colours)
        ``# [R, S, V, C]``, else None."""
        src = feats.sources
        cams = src.cameras
        pts = rays.points(z, unit_z=True)  # [R, S, 3]
        proj = project(cams, pts)
        C = self.cfg.feature_dim
        maps = feats.maps[:, half * C:(half + 1) * C]
        rgb_feat = gather([src.images.permute(0, 3, 1, 2), maps], proj, ["border", "zeros"])  # [R, S, V, 3+C]
        a = F.normalize(rays.origins[:, None, None] - pts[:, :, None], dim=-1)  # to target  [R, S, 1, 3]
        b = F.normalize(cams.centers[None, None] - pts[:, :, None], dim=-1)  # to sources [R, S, V, 3]
        ray_diff = torch.cat([F.normalize(a - b, dim=-1), (a * b).sum(-1, keepdim=True)], -1)
        mask = proj.mask  # [R, S, V]
        sig = None if signals is None else gather(signals.permute(0, 3, 1, 2).to(pts.dtype), proj, "border")  # [R, S, V, C]
        return rgb_feat, ray_diff, mask, sig

    def _pass(self, net: Aggregator, feats, rays, z, half, signals: Tensor | None = None,
              stands_for: Tensor | None = None, positions: Tensor | None = None, weights_out: bool = False):
        """One pass at depths ``z``; ``stands_for # [R, S]``: trained samples per rendered one (index code and
        density; None: one each, the trained sampling). ``weights_out``: add ``colour_weights`` and ``colour_depths``
        (:class:`~omnirecon.models.base.Capabilities`)."""
        rgb_feat, ray_diff, mask, sig = self._gather(feats, rays, z, half, signals)
        with net_autocast(z.device):
            extra = () if stands_for is None and positions is None else (stands_for, positions)
            sigma, blend = compiled(net)(rgb_feat, ray_diff, mask, *extra)
        sigma, blend = sigma.to(z.dtype), blend.to(z.dtype)
        w, _ = weights_from_alpha(alpha_from_density(sigma if stands_for is None else sigma * stands_for))
        sample_rgb = (blend[..., None] * rgb_feat[..., :3]).sum(-2)  # [R, S, 3]
        enough = (mask.sum(-1) >= 2).sum(-1) > min(8, z.shape[1] // 4)  # reference: > 8 samples seen twice
        out = {"rgb": composite(w, sample_rgb), "depth": (w * z).sum(-1), "weights": w, "z": z,
               "valid": enough, "acc": w.sum(-1)}
        if sig is not None:  # predict-then-blend: the colour blend weights, then the volume weights
            out["signal"] = composite(w, (blend[..., None] * sig).sum(-2))
        if weights_out:
            out["colour_weights"], out["colour_depths"] = w[..., None] * blend, z  # [R, S, V], [R, S]
        return out

    def render_rays(self, features: IBRNetFeatures, rays: Rays, jitter: bool = False,
                    signals: Tensor | None = None, fine_pass: bool | None = None, surface_samples: int = 0,
                    depths: Tensor | None = None, colour_weights: bool = False) -> dict[str, Tensor]:
        """Coarse then fine pass. ``signals # [V, H, W, C]`` (optional, per-source-view 2-D maps): also
        return ``signal # [R, C]``, the maps blended with the final pass's colour blend weights and
        composited with its volume weights, exactly as ``rgb`` (predict-then-blend; not normalised by
        ``acc``, see :mod:`omnirecon.lift.blend`). ``fine_pass`` and ``surface_samples`` change the
        output outside training (:class:`~omnirecon.models.base.Capabilities` ``passes``; None: the fine pass).
        ``depths # [R, S]``: one pass at these sample z-depths with the fine network (the coarse one when
        ``fine_pass`` is False), their density as trained and their index code at :func:`trained_positions`
        (surface-guided rendering, :mod:`omnirecon.models.guided`). ``colour_weights``: add the final pass's
        ``colour_weights`` and ``colour_depths`` (:class:`~omnirecon.models.base.Capabilities`)."""
        cfg = self.cfg
        if depths is not None:
            return self._guided(features, rays, depths, signals, fine_pass is False, colour_weights)
        nc, nf = cfg.coarse_samples, cfg.fine_samples
        if is_rendering() and not jitter:  # the checkpoint's render counts (fewer samples standing for the trained)
            nc, nf = cfg.render_coarse_samples or nc, cfg.render_fine_samples or nf
        z = coarse_depths(features.sources, rays, nc, jitter)
        fine_net = self.fine if fine_pass is not False or jitter else None  # False: depth maps from the coarse pass
        fewer = (nc, nf) != (cfg.coarse_samples, cfg.fine_samples)  # rendered samples stand for the trained ones
        coarse = self._pass(self.coarse, features, rays, z, 0, signals if fine_net is None else None,
                            torch.full_like(z, cfg.coarse_samples / nc) if fewer else None,
                            weights_out=colour_weights and fine_net is None)
        out = {f"{k}_coarse": v for k, v in coarse.items() if not k.startswith("colour_")}
        if fine_net is None:
            return {**out, **{k: v for k, v in coarse.items() if k not in ("weights", "z")}}
        stands_for = None
        if fewer and not surface_samples:
            z_fine, from_coarse = fine_depths(z, coarse["weights"], nf, jitter, origin=True)
            stands_for = torch.where(from_coarse, cfg.coarse_samples / nc, cfg.fine_samples / nf).to(z.dtype)
        else:
            z_fine = fine_depths(z, coarse["weights"], nf, jitter, surface_samples)
        fine = self._pass(self.fine, features, rays, z_fine, 1, signals, stands_for, weights_out=colour_weights)
        out.update({k: v for k, v in fine.items() if k not in ("weights", "z")})
        out["valid"] = fine["valid"] & coarse["valid"]
        return out

    def _guided(self, features: IBRNetFeatures, rays: Rays, z: Tensor, signals: Tensor | None,
                coarse: bool, weights_out: bool = False) -> dict[str, Tensor]:
        """One pass at the caller's z-depths ``z # [R, S]`` (the fine network unless ``coarse`` or there is none)."""
        net, half = (self.coarse, 0) if coarse or self.fine is None else (self.fine, 1)
        out = self._pass(net, features, rays, z, half, signals, positions=trained_positions(
            z, features.sources, self.cfg.coarse_samples, 0 if coarse else self.cfg.fine_samples),
            weights_out=weights_out)
        return {**{f"{k}_coarse": v for k, v in out.items() if k in ("rgb", "depth")},
                **{k: v for k, v in out.items() if k not in ("weights", "z")}}
