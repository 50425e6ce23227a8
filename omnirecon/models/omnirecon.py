"""Omni-Recon (Fu et al., ECCV 2024): a geometry branch for the SRDF, an IBR appearance branch for colour.

Faithful to ``shared/docs/omnirecon.md`` §1–5 (the released code, VolRecon/ReTR/GNT parts):

1. **Encoder** (§2.1): an FPN gives each source view a stride-4 appearance feature ``F_i`` and three
   pyramid maps ``p1, p2, p3`` (strides 2, 4, 8) that only build the volume.
2. **Feature volume** (§2.2): three lattices (``N^3``, ``(N/2)^3``, ``(N/4)^3``) over the volume box;
   each voxel centre is projected into every view, ``p_{l+1}`` sampled, and the masked mean and
   variance over views concatenated; a top-down 3-D decoder fuses the levels into ``V`` (``N^3``).
3. **Geometry branch** (§3): per sample ``x_k`` on a ray, view tokens ``e_ki = [f_i(x_k); v_k]``
   (``v_k`` the trilinear sample of ``V``), query ``h_k = max_i e_ki``, volume tokens
   ``g_k = Linear(v_k)``; ``B`` blocks of (cross-attention of each sample to the volume tokens of
   its ray, subtraction attention over the views with the relative-direction bias and a per-channel
   softmax, positional-encoding fusion in the first block, self-attention along the ray), all
   pre-LN with an FFN each; an MLP head gives the signed ray distance ``s_k`` (SRDF).
4. **Rendering** (§3.4): NeuS-style ``alpha`` from the SRDF with a learnable sharpness
   ``exp(10 theta)`` (:func:`~omnirecon.render.volume.alpha_from_sdf`), ``w = alpha T``; a coarse pass
   and a fine pass that re-runs the whole network on the coarse samples plus importance samples
   drawn from the detached coarse weights (§3.5).
5. **Appearance branch** (§4): ``omega = softmax_i MLP([ReLU(Linear(f_i)); u_k - u_ki])`` over the
   valid views; colour ``= sum_i omega_i c_i`` (source RGB). It sees only ``F_i`` and the relative
   direction: no volume feature and no geometry-branch token reaches it (tested by gradients).

Outputs of :meth:`OmniRecon.render_rays` (fine pass unless suffixed ``_coarse``): ``rgb # [R, 3]``,
``rgb_coarse``, ``depth`` (z-depth ``sum_k w_k z_k``, not normalised by the opacity, as the
reference) and ``depth_coarse # [R]``, ``weights``, ``z`` (sample z-depths), ``sdf # [R, S]``,
``blend # [R, K]`` (the per-sample ``omega`` composited with ``w``: how much each view contributes to
the pixel; sums to ``acc``), ``acc`` (opacity) and ``valid # [R]`` (more than 8 samples seen by at
least 3 views, in both passes). ``return_samples=True`` adds the per-sample ``blend_samples # [R, S, K]``.

Departures (documented choices, each a config field where it matters):

* **Samples** are placed linearly in *z-depth* over the sources' ``[near, far]`` (inverse depth
  for forward-facing rigs, as our IBRNet); the SRDF and its intervals use the matching ray
  *distance* ``t = z / cos``, and ``depth`` is z-depth (the reference renders ray distance and
  converts); the L1 depth loss is therefore on z-depth.
* **Volume box** (``volume_bounds``): the paper preset uses ``[-1, 1]^3`` of the unit-sphere frame
  (the reference); the tiny preset fits the lattice to the scene's content box (``Sources.bounds``,
  plus a margin), since a 32^3 lattice over the unit cube spends most voxels on empty space and
  leaves flat procedural scenes a handful of voxels thick.
* **Validity** of a sample is "in front of the camera and inside the image", with our pixel-centre
  convention (``align_corners=False`` everywhere, so no half-pixel shift); a ray is valid with more
  than ``min(8, S/4)`` samples seen by ``min(3, K)`` views (the reference: 3 of its 4 views).
* **Views that do not see a sample** get the reference's ``-1e9`` logits in both the appearance
  softmax and the subtraction attention (so a sample no view sees blends all views uniformly);
  source colours are sampled with border padding.
* **Training defaults** (``omnirecon train``): §11.2's 256 rays and Adam 5e-4 (the reference: 1024
  rays, 1e-3) and ``--depth-weight 0.1`` on the L1 depth terms (the reference weighs them 1).
* **BatchNorm without running averages** (``bn_running_stats=False``, both presets): every BN
  layer normalises with the current batch in eval mode too. A batch is one scene (its K source
  views in the 2-D encoder, its one volume in the 3-D decoder), so running averages mix scenes:
  in eval mode they shifted scenes whose colours differ from the training mean (with batch statistics the
  tiny preset's held-out depth error and PSNR on a procedural scene improved markedly).
* **Leftover transmittance** (``leftover``): the reference composites ``sum w c`` and lets a ray
  that finds no surface come out dark (``black``, both presets). ``far`` (the far bound is opaque, as
  NeRF's infinite last interval) and ``renormalize`` (``w / sum w``) are options. On validation seeds
  901000-901007 plus ethiopianHead (K = 3 / 10, ``cpu`` protocol) the shipped tiny checkpoint scores
  about the same with either, so ``black`` stays. ``backdrop`` gives ``far``'s colours but ``black``'s depth and
  opacity (meshing reads ``acc`` as confidence): with ``forward_box="cameras"`` and the fine pass it led ``black``
  on forward-rig seeds and fern (``python -m bench fern_gap``); with the shipped coarse pass the lead is gone
  (``bench/results/fern_gap_coarse.json``), so the shipped checkpoint keeps ``black``.
* **Tiny preset**: §11.2 widths (halved CNN, 16-d appearance feature, D = 32, 2 heads, FFN x2),
  a 32^3 lattice, 32 + 16 samples, 6 PE frequencies and no dropout (a short CPU budget).

Size: the model's two branches and its SDF renderer share one config and one state-dict layout that the shipped
checkpoints depend on (the feature volume: :mod:`omnirecon.models.feature_volume`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omnirecon.cameras import Cameras, closest_point_to_axes, nearest_views
from omnirecon.models.base import Capabilities, GeneralizableModel
from omnirecon.models.fast import compiled, grad_mode, net_autocast
from omnirecon.models.feature_volume import VolumeDecoder, lattice, mean_var_volume, volume_box
from omnirecon.models.gpnr import fourier
from omnirecon.models.pretrained import PyramidMaps
from omnirecon.models.projector import gather, project
from omnirecon.models.sampler import coarse_depths, fine_depths
from omnirecon.rays import Rays, Sources
from omnirecon.render.volume import alpha_from_sdf, composite, weights_from_alpha


@dataclass
class OmniReconConfig:
    """Omni-Recon hyper-parameters (defaults: the released code, ``omnirecon.md`` §2–5)."""

    num_views: int = 4
    """Source views K per target (4 in training, 3 at DTU test time)."""
    coarse_samples: int = 64
    """Samples per ray of the coarse pass (linear in depth, jittered in training)."""
    fine_samples: int = 64
    """Importance samples added for the fine pass (0: coarse pass only)."""
    render_fine_pass: bool = True
    """Outside training, render the fine pass unless a caller asks otherwise (``render_rays(fine_pass=None)``);
    False: the coarse pass only, a property measured per weights (the shipped omnirecon-tiny's coarse pass renders
    several times faster at no loss on held-out views: ``python -m bench tiny_levers``, BENCHMARKS "Render levers
    of the tiny presets"). Training renders both."""
    cnn_channels: tuple[int, int, int, int] = (16, 32, 64, 96)
    """FPN widths: stem (stride 1), layer1 (2), layer2 (4), layer3 (8)."""
    feature_dim: int = 32
    """Channels of the stride-4 appearance feature ``F_i``."""
    pyramid_channels: tuple[int, int, int] = (16, 16, 24)
    """Channels of the pyramid maps p1, p2, p3; the volume levels get twice as many (mean ‖ variance)."""
    volume_resolution: int = 144
    """Finest lattice side N (the others are N/2 and N/4; a multiple of 4, at least 8)."""
    volume_bounds: Literal["unit", "scene"] = "unit"
    """Volume box: ``[-1, 1]^3`` (reference) or the sources' content box plus ``volume_margin``
    (``unit`` when the sources carry no bounds)."""
    volume_margin: float = 0.05
    """Margin added to each side of a ``scene`` box, as a fraction of its largest half-extent."""
    forward_box: Literal["content", "cameras"] = "cameras"
    """A ``scene`` box on a forward-facing rig: the content box alone, or the content box grown to hold the
    source cameras' centres (``cameras``), so the lattice spans the space from the cameras to the content as
    on the procedural forward rigs the tiny preset was trained on, whose content box reaches the cameras.
    On fern (LLFF bounds: the box starts ~0.3 in front of the cameras) ``content`` made the geometry branch put
    an opaque layer near the near plane, below the non-learned floor; ``cameras`` scores above it (``cpu``
    protocol, K = 3). Object rigs are unchanged."""
    blocks: int = 2
    """Geometry-branch blocks B."""
    heads: int = 4
    """Heads of the cross-attention (to the volume) and the self-attention (along the ray)."""
    ffn_mult: int = 4
    """FFN hidden width as a multiple of the model width D."""
    pe_freqs: int = 10
    """Positional-encoding frequencies 2^0 .. 2^(L-1) (no pi factor, as the reference)."""
    dropout: float = 0.1
    """Dropout of the attention weights and the FFNs."""
    causal: bool = False
    """Causal mask in the self-attention along the ray (the reference's off-by-default option)."""
    deviation_init: float = 0.3
    """Initial ``theta`` of the SDF sharpness ``exp(10 theta)`` (about 20)."""
    blend_hidden: tuple[int, int] = (16, 8)
    """Hidden widths of the appearance MLP (``[z_i; u_k - u_ki]`` -> ... -> 1 logit)."""
    valid_views: int = 3
    """A sample counts towards ray validity when at least min(this, K) views see it."""
    valid_samples: int = 8
    """A ray is valid when more than min(this, S/4) of its samples are seen by enough views."""
    leftover: Literal["black", "far", "renormalize", "backdrop"] = "black"
    """Where the transmittance left after the last sample goes: nowhere (``black``, the reference: a ray
    that finds no surface comes out dark), to the last sample (``far``: alpha = 1 there, NeRF's infinite
    last interval, so the far bound acts as a backdrop) or spread over the samples (``renormalize``:
    ``w / sum w``). Applies to rgb, depth, blend and lifted signals alike. ``backdrop``: ``far`` for the colours
    (rgb and lifted signals) only; depth, opacity (``acc``, which meshing reads as confidence), weights and
    blend stay as ``black``, so a ray that finds no surface shows the far colour but adds no surface."""
    encoder: Literal["scratch", "vgg16", "alexnet"] = "scratch"
    """2-D encoder: the FPN trained from scratch, or a frozen pretrained backbone (HED's VGG16, ST-LPIPS's
    AlexNet) with small trainable adapters to the appearance feature and the three pyramid maps
    (:mod:`omnirecon.models.pretrained`)."""
    bn_running_stats: bool = False
    """BatchNorm keeps running averages for eval mode (the reference). False: it always normalises with
    the current batch (one scene's K source views; its one volume), so training and test agree."""
    render_views: int | None = None
    """Outside training (``render_view``), given more sources than this, render from the ``render_views`` sources
    nearest the target camera only (angle around the sources' look-at centre on object rigs, distance between
    centres otherwise, as the evaluation protocols pick sources), encoded on their own; dropped sources get zero
    ``blend``. None: every source. A render option for weights trained at one K (the shipped omnirecon-tiny:
    K = 4 only), measured in its model card."""

    @property
    def volume_dim(self) -> int:
        """Channels of the decoded volume ``V`` (the finest level's mean ‖ variance width)."""
        return 2 * self.pyramid_channels[0]

    @property
    def dim(self) -> int:
        """Model width D = appearance feature + volume feature."""
        return self.feature_dim + self.volume_dim


PRESETS = {
    "omnirecon-paper": OmniReconConfig(),
    "omnirecon-tiny": OmniReconConfig(coarse_samples=32, fine_samples=16, cnn_channels=(8, 16, 32, 48), feature_dim=16,
                                      pyramid_channels=(8, 8, 12), volume_resolution=32, volume_bounds="scene",
                                      heads=2, ffn_mult=2, pe_freqs=6, dropout=0.0),
}


# ---------------------------------------------------------------------- 2-D encoder (§2.1)
def _conv_bn(cin: int, cout: int, stride: int, relu: bool, running: bool) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Conv2d(cin, cout, 3, stride, 1, bias=False),
                               nn.BatchNorm2d(cout, track_running_stats=running)]
    return nn.Sequential(*layers, nn.ReLU()) if relu else nn.Sequential(*layers)


class ResBlock(nn.Module):
    """ConvBnReLU(3x3, stride) -> ConvBn(3x3) plus a shortcut (strided ConvBn when the shape changes), ReLU."""

    def __init__(self, cin: int, cout: int, stride: int, running: bool):
        super().__init__()
        self.body = nn.Sequential(_conv_bn(cin, cout, stride, True, running), _conv_bn(cout, cout, 1, False, running))
        self.skip = None if stride == 1 and cin == cout else _conv_bn(cin, cout, stride, False, running)

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.body(x) + (x if self.skip is None else self.skip(x)))


class FPNEncoder(nn.Module):
    """Images ``# [V, 3, H, W]`` -> appearance feature ``# [V, C, H/4, W/4]`` and pyramid maps p1, p2, p3."""

    def __init__(self, cfg: OmniReconConfig):
        super().__init__()
        c0, c1, c2, c3 = cfg.cnn_channels
        run = cfg.bn_running_stats
        self.stem = _conv_bn(3, c0, 1, True, run)
        self.layer1 = nn.Sequential(ResBlock(c0, c1, 2, run), ResBlock(c1, c1, 1, run))
        self.layer2 = nn.Sequential(ResBlock(c1, c2, 2, run), ResBlock(c2, c2, 1, run))
        self.layer3 = nn.Sequential(ResBlock(c2, c3, 2, run), ResBlock(c3, c3, 1, run))
        self.lateral = nn.Conv2d(c2, c3, 1)
        self.out = nn.Conv2d(c3, cfg.feature_dim, 3, padding=1)
        p1, p2, p3 = cfg.pyramid_channels
        self.pyramid = nn.ModuleList([nn.Conv2d(c1, p1, 3, padding=1), nn.Conv2d(c2, p2, 3, padding=1),
                                      nn.Conv2d(c3, p3, 3, padding=1)])

    def forward(self, x: Tensor) -> tuple[Tensor, list[Tensor]]:
        x1 = self.layer1(self.stem(x))  # stride 2
        x2 = self.layer2(x1)  # stride 4
        x3 = self.layer3(x2)  # stride 8
        top = F.interpolate(x3, size=x2.shape[-2:], mode="bilinear", align_corners=False) + self.lateral(x2)
        return self.out(top), [conv(m) for conv, m in zip(self.pyramid, (x1, x2, x3))]

    def appearance(self, x: Tensor, checkpoint: bool = False) -> Tensor:
        """The appearance feature of :meth:`forward` alone (the mesh path's: no pyramid maps), bit for bit. With
        ``checkpoint`` (and gradients on), each stage and residual block is a ``torch.utils.checkpoint`` segment:
        backward recomputes its activations instead of keeping them, so the graph of many large source views holds
        only the segments' outputs (one segment's activations at a time during backward). ``# [V, C, H/4, W/4]``"""
        if checkpoint and torch.is_grad_enabled():
            from torch.utils.checkpoint import checkpoint as ckpt

            run = lambda f, *a: ckpt(f, *a, use_reentrant=False)  # noqa: E731
        else:
            run = lambda f, *a: f(*a)  # noqa: E731
        x = run(self.stem, x)
        levels = []
        for layer in (self.layer1, self.layer2, self.layer3):
            for block in layer:
                x = run(block, x)
            levels.append(x)
        return run(self._head, levels[1], levels[2])

    def _head(self, x2: Tensor, x3: Tensor) -> Tensor:
        top = F.interpolate(x3, size=x2.shape[-2:], mode="bilinear", align_corners=False) + self.lateral(x2)
        return self.out(top)


# ---------------------------------------------------------------------- geometry branch (§3)
class SubtractionAttention(nn.Module):
    """GNT's view transformer attention (§3.3): per-channel softmax over views of ``MLP_a(k'_i - q' + p_i)``.

    ``q' = W_q q``, ``k'_i = W_k e_i``, ``v'_i = W_v k'_i`` (the value is computed from the projected
    key, as the reference), ``p_i = MLP_p(delta_d_i)``; ``out = W_o sum_i alpha_i * (v'_i + p_i)``.
    """

    def __init__(self, dim: int, dropout: float):
        super().__init__()
        hid = max(dim // 8, 1)
        self.q, self.k, self.v = (nn.Linear(dim, dim, bias=False) for _ in range(3))
        self.pos = nn.Sequential(nn.Linear(4, hid), nn.ReLU(), nn.Linear(hid, dim))
        self.score = nn.Sequential(nn.Linear(dim, hid), nn.ReLU(), nn.Linear(hid, dim))
        self.out = nn.Linear(dim, dim)
        self.drop = nn.Dropout(dropout)

    def forward(self, q: Tensor, views: Tensor, dirs: Tensor, mask: Tensor) -> Tensor:
        """``q # [..., D]``, ``views # [..., K, D]``, ``dirs # [..., K, 4]``, ``mask # [..., K]`` -> ``# [..., D]``."""
        q = self.q(q)
        k = self.k(views)
        v = self.v(k)
        p = self.pos(dirs)
        logits = self.score(k - q[..., None, :] + p).masked_fill(~mask[..., None], -1e9)  # [..., K, D]
        a = self.drop(torch.softmax(logits, dim=-2))  # per channel, over views
        return self.drop(self.out((a * (v + p)).sum(-2)))


def _ffn(dim: int, mult: int, dropout: float) -> nn.Sequential:
    """Pre-LN feed-forward (the residual is added by the caller)."""
    return nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, mult * dim), nn.ReLU(), nn.Dropout(dropout),
                         nn.Linear(mult * dim, dim), nn.Dropout(dropout))


class GeometryBlock(nn.Module):
    """Cross-attention to the ray's volume tokens, subtraction attention over views, optional PE fusion,
    self-attention along the ray; each attention pre-LN with a residual and its own FFN."""

    def __init__(self, cfg: OmniReconConfig, fuse_position: bool):
        super().__init__()
        D, drop = cfg.dim, cfg.dropout
        self.cross_norm = nn.LayerNorm(D)
        self.cross = nn.MultiheadAttention(D, cfg.heads, dropout=drop, batch_first=True)
        self.cross_ffn = _ffn(D, cfg.ffn_mult, drop)
        self.view_norm = nn.LayerNorm(D)
        self.view = SubtractionAttention(D, drop)
        self.view_ffn = _ffn(D, cfg.ffn_mult, drop)
        pe_dim = 3 * (1 + 2 * cfg.pe_freqs)
        self.fuse = nn.Sequential(nn.Linear(D + pe_dim, D), nn.ReLU(), nn.Linear(D, D)) if fuse_position else None
        self.ray_norm = nn.LayerNorm(D)
        self.ray = nn.MultiheadAttention(D, cfg.heads, dropout=drop, batch_first=True)
        self.ray_ffn = _ffn(D, cfg.ffn_mult, drop)

    def forward(self, h: Tensor, tokens: Tensor, views: Tensor, dirs: Tensor, mask: Tensor, pe: Tensor,
                causal: Tensor | None) -> Tensor:
        """``h, tokens # [R, S, D]``, ``views # [R, S, K, D]``, ``dirs # [R, S, K, 4]``, ``mask # [R, S, K]``,
        ``pe # [R, S, P]`` -> ``# [R, S, D]``."""
        h = h + self.cross(self.cross_norm(h), tokens, tokens, need_weights=False)[0]
        h = h + self.cross_ffn(h)
        h = h + self.view(self.view_norm(h), views, dirs, mask)
        h = h + self.view_ffn(h)
        if self.fuse is not None:
            h = self.fuse(torch.cat([h, pe], -1))  # no residual
        q = self.ray_norm(h)
        h = h + self.ray(q, q, q, attn_mask=causal, need_weights=False)[0]
        return h + self.ray_ffn(h)


class GeometryBranch(nn.Module):
    """Per-sample view tokens and volume features -> SRDF ``# [R, S]``."""

    def __init__(self, cfg: OmniReconConfig):
        super().__init__()
        D = cfg.dim
        self.cfg = cfg
        self.tokens = nn.Linear(cfg.volume_dim, D)
        self.blocks = nn.ModuleList([GeometryBlock(cfg, fuse_position=b % 2 == 0) for b in range(cfg.blocks)])
        self.head = nn.Sequential(nn.LayerNorm(D), nn.Linear(D, D // 2), nn.ReLU(), nn.Linear(D // 2, D // 4),
                                  nn.ReLU(), nn.Linear(D // 4, 1))

    def forward(self, feat: Tensor, vol: Tensor, dirs: Tensor, mask: Tensor, points: Tensor) -> Tensor:
        """``feat # [R, S, K, C]`` (zero where invalid), ``vol # [R, S, Cv]``, ``dirs # [R, S, K, 4]``,
        ``mask # [R, S, K]``, ``points # [R, S, 3]`` -> SRDF ``# [R, S]``."""
        views = torch.cat([feat, vol[:, :, None].expand(-1, -1, feat.shape[2], -1)], -1)  # [R, S, K, D]
        h = views.amax(2)  # [R, S, D]
        tokens = self.tokens(vol)
        pe = fourier(points, self.cfg.pe_freqs)  # gamma(x): identity + sin/cos at 2^0..2^(L-1), no pi
        S = h.shape[1]
        causal = torch.ones(S, S, dtype=torch.bool, device=h.device).triu(1) if self.cfg.causal else None
        for block in self.blocks:
            h = block(h, tokens, views, dirs, mask, pe, causal)
        return self.head(h)[..., 0]


# ---------------------------------------------------------------------- appearance branch (§4)
class AppearanceBranch(nn.Module):
    """``omega = softmax_i MLP([ReLU(Linear(f_i)); u_k - u_ki])`` over valid views; sees nothing else."""

    def __init__(self, cfg: OmniReconConfig):
        super().__init__()
        C = cfg.feature_dim
        h1, h2 = cfg.blend_hidden
        self.proj = nn.Linear(C, C)
        self.mlp = nn.Sequential(nn.Linear(C + 3, h1), nn.ReLU(), nn.Linear(h1, h2), nn.ReLU(), nn.Linear(h2, 1))

    def forward(self, feat: Tensor, rel_dir: Tensor, mask: Tensor) -> Tensor:
        """``feat # [..., K, C]``, ``rel_dir # [..., K, 3]``, ``mask # [..., K]`` -> ``omega # [..., K]``."""
        logits = self.mlp(torch.cat([F.relu(self.proj(feat)), rel_dir], -1))[..., 0]
        return torch.softmax(logits.masked_fill(~mask, -1e9), -1)


# ---------------------------------------------------------------------- the model
@dataclass
class OmniReconFeatures:
    """Encoded sources: what ``render_rays`` needs, computed once per scene."""

    sources: Sources
    maps: Tensor
    """Stride-4 appearance features ``F_i``. ``# [K, C, H/4, W/4]``"""
    volume: Tensor
    """Decoded feature volume ``V`` over ``box``. ``# [1, Cv, N, N, N]`` (z, y, x)"""
    box: Tensor
    """The volume's ``[min, max]`` corners. ``# [2, 3]``"""


class PointSamples(NamedTuple):
    """What one pass gathers at its sample points (``R`` rays, ``S`` samples, ``K`` views)."""

    points: Tensor
    """``# [R, S, 3]``"""
    feat: Tensor
    """``F_i`` at each point, zero in views that do not see it. ``# [R, S, K, C]``"""
    rgb: Tensor
    """Source colours. ``# [R, S, K, 3]``"""
    mask: Tensor
    """The view sees the point (in front, inside the image). ``# [R, S, K]``"""
    dirs: Tensor
    """``[u_k - u_ki; <u_k, u_ki>]``: target vs source viewing directions. ``# [R, S, K, 4]``"""


def nearest_sources(sources: Sources, camera: Cameras, n: int) -> Tensor:
    """Indices of the ``n`` sources nearest the one ``camera``, nearest first: by the angle around the point
    closest to the sources' optical axes on object rigs, by the distance between centres otherwise. ``# [n]``"""
    cams = sources.cameras
    target = camera.to(device=cams.c2w.device, dtype=cams.c2w.dtype)
    if sources.rig == "object":
        return nearest_views(target, cams, n, by="angle", center=closest_point_to_axes(cams))[0]
    return nearest_views(target, cams, n, by="distance")[0]


class OmniRecon(GeneralizableModel):
    capabilities = Capabilities(depth=True, signals=True, jitter=True, appearance=True, passes=True, guided=True,
                                colour_weights=True)

    def __init__(self, cfg: OmniReconConfig):
        super().__init__()
        if cfg.volume_resolution % 4 or cfg.volume_resolution < 8:
            raise ValueError(f"volume_resolution must be a multiple of 4, at least 8, got {cfg.volume_resolution}")
        self.cfg = cfg
        self.encoder = FPNEncoder(cfg) if cfg.encoder == "scratch" else \
            PyramidMaps(cfg.encoder, cfg.feature_dim, cfg.pyramid_channels)
        self.volume = VolumeDecoder(cfg)
        self.geometry = GeometryBranch(cfg)
        self.appearance = AppearanceBranch(cfg)
        self.deviation = nn.Parameter(torch.tensor(cfg.deviation_init))

    @property
    def sharpness(self) -> Tensor:
        """``iota = exp(10 theta)``: the sigmoid slope of the SRDF -> alpha conversion."""
        return torch.exp(10.0 * self.deviation)

    # ------------------------------------------------------------------ encode
    def encode(self, sources: Sources) -> OmniReconFeatures:
        cfg = self.cfg
        feat, pyramid = self.encoder(sources.images.permute(0, 3, 1, 2))
        box = volume_box(sources, cfg.volume_bounds, cfg.volume_margin, cfg.forward_box)
        levels = []
        for level, maps in enumerate(pyramid):
            res = cfg.volume_resolution >> level
            levels.append(mean_var_volume(maps, sources.cameras, lattice(box, res), res))
        return OmniReconFeatures(sources, feat, self.volume(levels), box)

    def encode_appearance(self, sources: Sources, checkpoint: bool = False) -> OmniReconFeatures:
        """What the appearance branch reads (:meth:`shade`, :meth:`gather`: the mesh path, ``finetune``): the maps
        ``F_i`` of :meth:`encode`, bit for bit (:meth:`FPNEncoder.appearance`: no pyramid maps), without the feature
        volume, which only :meth:`render_rays` reads (``volume`` and ``box`` are left empty). Differentiable;
        ``checkpoint``: recompute the encoder's activations in backward instead of keeping them (large source sets)."""
        images = sources.images.permute(0, 3, 1, 2)  # [K, 3, H, W]
        if isinstance(self.encoder, FPNEncoder):
            feat = self.encoder.appearance(images, checkpoint=checkpoint)  # [K, C, H/4, W/4]
        else:  # a pretrained encoder (PyramidMaps): its full pass
            feat, _ = self.encoder(images)
        return OmniReconFeatures(sources, feat, feat.new_zeros(0), feat.new_zeros(2, 3))

    def render_view(self, features: OmniReconFeatures, camera: Cameras, chunk: int = 4096,
                    signals: Tensor | None = None, **kw) -> dict[str, Tensor]:
        """:meth:`GeneralizableModel.render_view`, from the ``cfg.render_views`` sources nearest ``camera`` when
        there are more (outside training; ``blend`` and ``colour_weights`` keep one channel per given source, zero
        for the dropped)."""
        src, n = features.sources, self.cfg.render_views
        if not n or self.training or len(src.cameras) <= n:
            return super().render_view(features, camera, chunk, signals, **kw)
        keep = nearest_sources(src, camera, n)  # [n]
        with grad_mode():
            sub = self.encode(Sources(src.images[keep], src.cameras[keep], src.near, src.far, src.rig, src.bounds))
        out = super().render_view(sub, camera, chunk, None if signals is None else signals[keep], **kw)
        wide = {}
        for key in ("blend", "colour_weights"):  # one channel per given source, zero for the dropped
            if key in out:
                wide[key] = out[key].new_zeros(*out[key].shape[:-1], len(src.cameras))  # [..., K]
                wide[key][..., keep] = out[key]
        return {**out, **wide}

    # ------------------------------------------------------------------ per-sample inputs
    def gather(self, features: OmniReconFeatures, points: Tensor, origins: Tensor) -> PointSamples:
        """Sample the source views at ``points # [R, S, 3]`` seen from ``origins # [R, 3]`` (the target camera)."""
        src = features.sources
        cams = src.cameras
        proj = project(cams, points)
        mask = proj.mask  # [R, S, K]
        feat = gather(features.maps, proj, "zeros") * mask[..., None]  # [R, S, K, C]
        rgb = gather(src.images.permute(0, 3, 1, 2), proj, "border")  # [R, S, K, 3]
        u = F.normalize(points - origins[:, None], dim=-1)[:, :, None]  # target -> point  [R, S, 1, 3]
        u_src = F.normalize(points[:, :, None] - cams.centers.to(points.dtype), dim=-1)  # sources -> point [R, S, K, 3]
        dirs = torch.cat([u - u_src, (u * u_src).sum(-1, keepdim=True)], -1)
        return PointSamples(points, feat, rgb, mask, dirs)

    def volume_features(self, features: OmniReconFeatures, points: Tensor) -> Tensor:
        """Trilinear samples of ``V`` at ``points # [R, S, 3]`` (zero outside the box). ``# [R, S, Cv]``"""
        lo, hi = features.box
        g = ((points - lo) / (hi - lo) * 2 - 1).to(features.volume.dtype)  # (x, y, z) in [-1, 1]
        v = F.grid_sample(features.volume, g.reshape(1, 1, 1, -1, 3), align_corners=False, padding_mode="zeros")
        return v.reshape(v.shape[1], *points.shape[:2]).permute(1, 2, 0)

    def blend_weights(self, samples: PointSamples) -> Tensor:
        """The appearance branch alone: ``omega # [R, S, K]`` from ``F_i`` and the viewing directions."""
        return self.appearance(samples.feat, samples.dirs[..., :3], samples.mask)

    def shade(self, features: OmniReconFeatures, points: Tensor, origins: Tensor,
              visible: Tensor | None = None) -> dict[str, Tensor]:
        """Colour surface ``points # [P, 3]`` seen from ``origins # [P, 3]`` with the appearance branch only
        (§7: one point per pixel, no geometry branch). Returns ``rgb # [P, 3]``, ``blend # [P, K]`` and
        ``valid # [P]`` (some view sees the point).

        ``visible # [P, K]`` bool (optional, e.g. a depth test against each source's rasterized depth):
        views where it is False are masked out of the blend like views the point projects outside of."""
        samples = self.gather(features, points[:, None], origins)
        if visible is not None:
            mask = samples.mask & visible[:, None].to(samples.mask.device)  # [P, 1, K]
            samples = samples._replace(mask=mask, feat=samples.feat * mask[..., None])
        omega = self.blend_weights(samples)  # [P, 1, K]
        rgb = (omega[..., None] * samples.rgb).sum(-2)[:, 0]
        return {"rgb": rgb, "blend": omega[:, 0], "valid": samples.mask[:, 0].any(-1)}

    # ------------------------------------------------------------------ render
    def sample_signals(self, features: OmniReconFeatures, points: Tensor, signals: Tensor) -> Tensor:
        """Per-view 2-D maps ``signals # [K, H, W, C]`` at ``points # [R, S, 3]``, projected and sampled exactly
        as :meth:`gather` samples the source colours (bilinear, border padding). ``# [R, S, K, C]``"""
        return gather(signals.permute(0, 3, 1, 2).to(points.dtype), project(features.sources.cameras, points), "border")

    def _pass(self, features: OmniReconFeatures, rays: Rays, z: Tensor,
              signals: Tensor | None = None, weights_out: bool = False) -> tuple[dict[str, Tensor], Tensor]:
        """One pass at sample z-depths ``z # [R, S]``: outputs and the per-sample ``omega # [R, S, K]``.
        With ``signals # [K, H, W, C]`` the outputs add ``signal # [R, C]``: the maps blended with ``omega``
        and composited with ``w``, exactly as ``rgb`` (predict-then-blend). ``weights_out``: they add ``colour_weights``
        and ``colour_depths`` (:class:`~omnirecon.models.base.Capabilities`)."""
        t = rays.distances(z)  # [R, S]
        points = rays.points(z)  # [R, S, 3]
        samples = self.gather(features, points, rays.origins)
        vol = self.volume_features(features, points)
        with net_autocast(points.device):
            sdf = compiled(self.geometry)(samples.feat, vol, samples.dirs, samples.mask, points)  # [R, S]
            omega = compiled(self.appearance)(samples.feat, samples.dirs[..., :3], samples.mask)  # [R, S, K]
        sdf, omega = sdf.to(points.dtype), omega.to(points.dtype)
        alpha = alpha_from_sdf(sdf, t, self.sharpness)  # [R, S]
        if self.cfg.leftover == "far":
            alpha = torch.cat([alpha[:, :-1], torch.ones_like(alpha[:, -1:])], -1)
        w, trans = weights_from_alpha(alpha, eps=1e-7)
        if self.cfg.leftover == "renormalize":
            w = w / w.sum(-1, keepdim=True).clamp_min(1e-6)
        # backdrop: colours only take what "far" would give the last sample; depth, acc and weights stay "black"
        w_col = torch.cat([w[:, :-1], trans[:, -1:]], -1) if self.cfg.leftover == "backdrop" else w  # [R, S]
        colour = (omega[..., None] * samples.rgb).sum(-2)  # [R, S, 3]
        K, S = samples.mask.shape[-1], z.shape[1]
        seen = samples.mask.sum(-1) >= min(self.cfg.valid_views, K)  # [R, S]
        valid = seen.sum(-1) > min(self.cfg.valid_samples, S // 4)
        out = {"rgb": composite(w_col, colour), "depth": (w * z).sum(-1), "weights": w, "z": z, "sdf": sdf,
               "blend": (w[..., None] * omega).sum(1), "acc": w.sum(-1), "valid": valid}
        if signals is not None:
            out["signal"] = composite(w_col, (omega[..., None] * self.sample_signals(features, points, signals)).sum(-2))
        if weights_out:
            out["colour_weights"], out["colour_depths"] = w_col[..., None] * omega, z  # [R, S, K], [R, S]
        return out, omega

    def render_rays(self, features: OmniReconFeatures, rays: Rays, jitter: bool = False,
                    return_samples: bool = False, signals: Tensor | None = None, fine_pass: bool | None = None,
                    surface_samples: int = 0, depths: Tensor | None = None,
                    colour_weights: bool = False) -> dict[str, Tensor]:
        """Coarse pass, then the fine pass on the coarse + importance samples (see the module docstring for
        the outputs). ``depths # [R, S]``: one pass at these sample z-depths instead (surface-guided rendering,
        :mod:`omnirecon.models.guided`; ``rgb_coarse`` and ``depth_coarse`` are that pass's). ``jitter``:
        stratified coarse samples and random importance samples (training).
        ``signals # [K, H, W, C]`` (per-source-view 2-D maps, optional) adds ``signal # [R, C]`` from the
        final pass: predict-then-blend with the RGB weights (not normalised by ``acc``; see
        :mod:`omnirecon.lift.blend`). ``fine_pass`` and ``surface_samples`` change the output outside
        training (:class:`~omnirecon.models.base.Capabilities` ``passes``; None: ``cfg.render_fine_pass``).
        ``colour_weights``: add the final pass's ``colour_weights`` and ``colour_depths`` (``Capabilities``)."""
        cfg = self.cfg
        z = coarse_depths(features.sources, rays, cfg.coarse_samples, jitter) if depths is None else depths  # [R, S]
        fine_pass = cfg.render_fine_pass if fine_pass is None else fine_pass
        # fine_pass=False: coarse depth maps; depths: the caller's samples, one pass
        coarse_only = depths is not None or cfg.fine_samples == 0 or not (fine_pass or jitter)
        coarse, omega = self._pass(features, rays, z, signals if coarse_only else None, colour_weights and coarse_only)
        if coarse_only:
            out = dict(coarse)
        else:
            z_fine = fine_depths(z, coarse["weights"], cfg.fine_samples, jitter, surface_samples)
            out, omega = self._pass(features, rays, z_fine, signals, colour_weights)
            out["valid"] = out["valid"] & coarse["valid"]
        out["rgb_coarse"], out["depth_coarse"] = coarse["rgb"], coarse["depth"]
        if return_samples:
            out["blend_samples"] = omega
        return out
