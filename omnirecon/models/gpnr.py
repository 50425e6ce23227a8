"""GPNR: generalizable patch-based neural rendering (Suhail et al., ECCV 2022).

Faithful to the authors' code (``shared/docs/gpnr_ibrnet.md`` Part A) with three fixes, each a
documented departure: the canonical frame is a proper rigid transform (the reference divides by
the squared norm); invalid projections (outside the image or behind the camera) are masked in all
attention and pooling steps (the reference clamps them to the border and never masks); the
relative pose is the true pose of each source camera in the canonical frame (the reference
subtracts a world-space centre from a camera-space translation). Sampling is bilinear at the
exact projection (the reference rounds to the nearest pixel).

Pipeline per target ray (``R`` rays, ``K`` source views, ``M`` samples, width ``D``):

1. ``M`` points at z-depths linear in ``[near, far]``; each is projected into every source view.
2. Key token per (view, point): Fourier(canonical source ray) ‖ Fourier(canonical point) ‖
   patch feature (a linear ``P x P`` convolution + ReLU, bilinearly sampled) ‖ centre RGB ‖
   relative pose (12) -> Linear -> ``D``. The query token is Fourier(canonical target ray),
   a constant (0, 0, 1, 0, 0, 0) once canonicalised, so it acts as a learned token.
3. Stage 1 attends across the ``K`` views at each depth; stage 2 along each epipolar line
   (``M`` points + query) per view -> ``alpha`` over points; stage 3 across the views (+ query)
   -> ``beta`` over views.
4. ``sigmoid(Linear(sum_k beta_k g_k))`` (feature head) and ``sum_k beta_k sum_m alpha_km rgb_km``
   (blended source colours, also returned as ``rgb_blend``); train on both. ``output`` picks which one
   is ``rgb`` (the other is ``rgb_aux``): the paper preset the feature head, the tiny preset the colours.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omnirecon.cameras import canonical_transform, plucker
from omnirecon.models.base import Capabilities, GeneralizableModel
from omnirecon.models.fast import compiled, is_rendering, net_autocast
from omnirecon.models.pretrained import SingleMap
from omnirecon.models.projector import gather, project
from omnirecon.rays import Rays, Sources


@dataclass
class GPNRConfig:
    """GPNR hyper-parameters and the seed's ablation switches."""

    num_views: int = 10
    """Source views K used per target ray."""
    num_samples: int = 127
    """Points M along each target ray (linear in z-depth between near and far)."""
    patch_size: int = 11
    """Side P of the square patch that is linearly projected (a P x P convolution)."""
    patch_channels: int = 32
    """Output channels of the patch projection."""
    dim: int = 256
    """Token width D."""
    mlp_dim: int = 256
    """Hidden width of each transformer MLP."""
    heads: int = 1
    """Attention heads."""
    layers: tuple[int, int, int] = (8, 8, 8)
    """Layers of the visual (across views), epipolar (along the ray) and view transformers."""
    ray_freqs: int = 4
    """Fourier frequencies for the ray encoding (2^0 .. 2^(n-1))."""
    point_freqs: int = 10
    """Fourier frequencies for the point encoding."""
    ray_param: Literal["plucker", "lightslab", "twosphere"] = "plucker"
    """Ray parameterisation: Plücker (default), light slab (two planes z = near, z = far of the
    target ray; forward-facing scenes) or two-sphere (the two intersections with the bounding sphere)."""
    visual_transformer: bool = True
    """Ablation: stage 1 (attention across views at each depth) on/off."""
    canonical_rays: bool = True
    """Ablation: express source/target rays in the target ray's canonical frame (else world)."""
    canonical_coords: bool = True
    """Ablation: express sample points and relative poses in the canonical frame (else world)."""
    output: Literal["features", "colors"] = "features"
    """Which prediction is ``rgb``: the feature head (GPNR) or the blended source colours; the other is
    ``rgb_aux``, and ``rgb_blend`` is always the blended colours."""
    mask_invalid: bool = True
    """Mask projections outside the image or behind the camera (the reference code does not)."""
    scene_radius: float = 1.0
    """Radius of the bounding sphere for the two-sphere parameterisation (scene units)."""
    render_samples: int | None = None
    """Points per ray inside ``render_view`` (rendering outside training) instead of ``num_samples``: a render
    option measured on some weights (the shipped gpnr-tiny: 24 instead of its 32). None: ``num_samples``."""
    render_bf16: bool = False
    """Inside ``render_view``, the transformers under bf16 autocast when ``FastPaths.bf16_render`` leaves the
    choice to the model (its default, None) and the device computes bf16 natively (:func:`~omnirecon.models.fast.
    native_bf16`): the shipped gpnr-tiny with 24 samples renders several times faster than its reference twin at
    the same held-out scores (``python -m bench tiny_levers``, on a CPU with avx512_bf16; BENCHMARKS "Render
    levers of the tiny presets")."""
    encoder: Literal["scratch", "vgg16", "alexnet"] = "scratch"
    """Patch features: the P x P linear projection trained from scratch, or a frozen pretrained backbone
    (HED's VGG16, ST-LPIPS's AlexNet) with a small trainable adapter to ``patch_channels`` at full
    resolution (:mod:`omnirecon.models.pretrained`)."""


PRESETS = {
    "gpnr-paper": GPNRConfig(),
    "gpnr-tiny": GPNRConfig(num_views=5, num_samples=32, patch_size=7, patch_channels=16, dim=64, mlp_dim=128,
                            heads=2, layers=(2, 2, 2), ray_freqs=4, point_freqs=6, output="colors"),
}
"""``gpnr-tiny`` renders the blended source colours: at the tiny CPU budget the feature head is far
behind (validation seeds 901000-901007, K = 3 / 10, shipped checkpoint). Both heads train with equal weight, so the choice changes nothing in training
but which one is ``rgb`` (the reference code has the same switch, ``eval.return_coarse``)."""


def fourier(x: Tensor, freqs: int) -> Tensor:
    """``[x, sin(2^l x), cos(2^l x)]`` for ``l < freqs``. ``# [..., C] -> [..., C (1 + 2 freqs)]``"""
    if freqs == 0:
        return x
    scales = 2.0 ** torch.arange(freqs, dtype=x.dtype, device=x.device)
    xs = (x[..., None, :] * scales[:, None]).flatten(-2)
    return torch.cat([x, torch.sin(xs), torch.cos(xs)], dim=-1)


@dataclass
class GPNRFeatures:
    """Encoded sources: what ``render_rays`` needs, computed once per scene."""

    sources: Sources
    patches: Tensor
    """Patch projections of every source image. ``# [V, C, H, W]``"""


def _transformer(dim: int, mlp: int, heads: int, layers: int) -> nn.Module:
    if layers == 0:
        return nn.Identity()
    layer = nn.TransformerEncoderLayer(dim, heads, mlp, dropout=0.0, activation="gelu", batch_first=True,
                                       norm_first=False)  # post-LN, as the reference
    return nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)


def _run(block: nn.Module, x: Tensor, pad: Tensor | None, bf16: bool = False) -> Tensor:
    """Apply a transformer with key padding ``pad # [B, L]`` (True = ignore); rows never all-masked.
    ``bf16``: the model's own choice of bf16 autocast while rendering (see :func:`net_autocast`)."""
    if isinstance(block, nn.Identity):
        return x
    if pad is not None:
        pad = pad & ~pad.all(dim=1, keepdim=True)  # nothing to attend to: attend to everything
    with net_autocast(x.device, bf16):
        return compiled(block)(x, src_key_padding_mask=pad).to(x.dtype)


class GPNR(GeneralizableModel):
    capabilities = Capabilities(depth=True, signals=True, guided=True, colour_weights=True)

    def __init__(self, cfg: GPNRConfig):
        super().__init__()
        self.cfg = cfg
        ray_dim = {"plucker": 6, "lightslab": 4, "twosphere": 6}[cfg.ray_param] * (1 + 2 * cfg.ray_freqs)
        point_dim = 3 * (1 + 2 * cfg.point_freqs)
        self.patch = nn.Conv2d(3, cfg.patch_channels, cfg.patch_size, padding=cfg.patch_size // 2) \
            if cfg.encoder == "scratch" else SingleMap(cfg.encoder, 1, cfg.patch_channels)
        self.key_proj = nn.Linear(ray_dim + point_dim + cfg.patch_channels + 3 + 12, cfg.dim)
        self.query_proj = nn.Linear(ray_dim, cfg.dim)
        self.query_proj2 = nn.Linear(ray_dim, cfg.dim)
        self.view_proj = nn.Linear(cfg.dim, cfg.dim)
        self.visual = _transformer(cfg.dim, cfg.mlp_dim, cfg.heads, cfg.layers[0] if cfg.visual_transformer else 0)
        self.epipolar = _transformer(cfg.dim, cfg.mlp_dim, cfg.heads, cfg.layers[1])
        self.view = _transformer(cfg.dim, cfg.mlp_dim, cfg.heads, cfg.layers[2])
        self.alpha_score = nn.Linear(2 * cfg.dim, 1)
        self.beta_score = nn.Linear(2 * cfg.dim, 1)
        self.rgb_head = nn.Linear(cfg.dim, 3)

    # ------------------------------------------------------------------ encode
    def encode(self, sources: Sources) -> GPNRFeatures:
        images = sources.images.permute(0, 3, 1, 2)  # [V, 3, H, W]
        return GPNRFeatures(sources, F.relu(self.patch(images)))

    # ------------------------------------------------------------------ encodings
    def _ray_code(self, o: Tensor, d: Tensor, near: float, far: float) -> Tensor:
        """Encode rays ``o, d # [..., 3]`` (already in the frame they should be described in)."""
        cfg = self.cfg
        if cfg.ray_param == "plucker":
            code = plucker(o, d)
        elif cfg.ray_param == "lightslab":
            dz = torch.where(d[..., 2:].abs() < 1e-6, torch.full_like(d[..., 2:], 1e-6), d[..., 2:])
            a = o[..., :2] + d[..., :2] * (near - o[..., 2:]) / dz
            b = o[..., :2] + d[..., :2] * (far - o[..., 2:]) / dz
            code = torch.cat([a, b], -1) / max(far, 1e-6)
        else:  # two-sphere: entry and exit points of the bounding sphere (closest points if missed)
            r = cfg.scene_radius
            b = (o * d).sum(-1, keepdim=True)
            c = (o * o).sum(-1, keepdim=True) - r * r
            disc = (b * b - c).clamp_min(0).sqrt()
            code = torch.cat([o + d * (-b - disc), o + d * (-b + disc)], -1) / r
        return fourier(code, cfg.ray_freqs)

    # ------------------------------------------------------------------ render
    def render_rays(self, features: GPNRFeatures, rays: Rays, signals: Tensor | None = None,
                    depths: Tensor | None = None, colour_weights: bool = False) -> dict[str, Tensor]:
        """Render rays. ``signals # [K, H, W, C]`` (optional, per-source-view 2-D maps): also return
        ``signal # [R, C] = sum_k beta_k sum_m alpha_km s_km``, the maps sampled exactly as the colours
        and blended with the weights of ``rgb_aux`` (predict-then-blend). ``depths # [R, M]``: the points' z-depths
        per ray instead of the linear ones (surface-guided rendering, :mod:`omnirecon.models.guided`).
        ``colour_weights``: with ``cfg.output == "colors"``, add ``colour_weights # [R, M, K]`` (``beta_k alpha_km``) and ``colour_depths
        # [R, M]`` (:class:`~omnirecon.models.base.Capabilities`)."""
        cfg = self.cfg
        src = features.sources
        cams = src.cameras
        M = cfg.render_samples if cfg.render_samples and is_rendering() else cfg.num_samples
        M = M if depths is None else depths.shape[1]
        K, R = len(cams), len(rays)
        dtype = features.patches.dtype

        # 1. samples along the target rays, linear in z-depth (or the caller's)
        z = torch.linspace(src.near, src.far, M, dtype=dtype, device=rays.origins.device) if depths is None \
            else depths.to(dtype)  # [M] or [R, M]
        dist = rays.distances(z)  # [R, M]
        pts = rays.points(z)  # [R, M, 3]

        # 2. project into every source view and sample patch features and colours
        proj = project(cams, pts, dtype)
        valid = proj.mask.transpose(1, 2) if cfg.mask_invalid else torch.ones(R, K, M, dtype=torch.bool,
                                                                               device=pts.device)  # [R, K, M]
        feat = gather(features.patches, proj, "zeros").transpose(1, 2)  # [R, K, M, C]
        rgb = gather(src.images.permute(0, 3, 1, 2), proj, "border").transpose(1, 2)  # [R, K, M, 3]

        # 3. canonical frame per target ray; source rays through each point, points, relative poses
        T = canonical_transform(rays.origins, rays.directions, rays.up)  # [R, 4, 4]
        Rc, tc = T[:, :3, :3], T[:, :3, 3]  # [R, 3, 3], [R, 3]
        centres = cams.centers  # [K, 3]
        src_d = F.normalize(pts[:, None] - centres[None, :, None], dim=-1)  # [R, K, M, 3]
        src_o = centres[None, :, None].expand_as(src_d)
        if cfg.canonical_rays:
            src_o_c = torch.einsum("rij,rkmj->rkmi", Rc, src_o) + tc[:, None, None]
            src_d_c = torch.einsum("rij,rkmj->rkmi", Rc, src_d)
            tgt_o, tgt_d = torch.zeros_like(rays.origins), torch.zeros_like(rays.directions)
            tgt_d[:, 2] = 1
        else:
            src_o_c, src_d_c, tgt_o, tgt_d = src_o, src_d, rays.origins, rays.directions
        if cfg.canonical_coords:
            pts_c = torch.zeros_like(pts)
            pts_c[..., 2] = dist  # the target ray is the z axis
            rel_R = torch.einsum("rij,kjl->rkil", Rc, cams.R)  # [R, K, 3, 3]
            rel_t = torch.einsum("rij,kj->rki", Rc, centres) + tc[:, None]  # [R, K, 3]
        else:
            pts_c = pts
            rel_R = cams.R[None].expand(R, -1, -1, -1)
            rel_t = centres[None].expand(R, -1, -1)
        rel = torch.cat([rel_R.flatten(-2), rel_t], -1)  # [R, K, 12]

        # 4. tokens
        ray_code = self._ray_code(src_o_c, src_d_c, src.near, src.far)  # [R, K, M, Dr]
        keys = torch.cat([
            ray_code, fourier(pts_c, cfg.point_freqs)[:, None].expand(-1, K, -1, -1),
            feat, rgb, rel[:, :, None].expand(-1, -1, M, -1),
        ], -1)
        keys = self.key_proj(keys.to(dtype))  # [R, K, M, D]
        q_code = self._ray_code(tgt_o, tgt_d, src.near, src.far)  # [R, Dr]
        query = self.query_proj(q_code)[:, None, None].expand(-1, K, 1, -1)  # [R, K, 1, D]
        x = torch.cat([query, keys], 2)  # [R, K, M+1, D]
        pad = torch.cat([torch.zeros_like(valid[..., :1]), ~valid], 2)  # [R, K, M+1] True = ignore
        D = cfg.dim

        # stage 1: across views at each depth
        x = x.transpose(1, 2).reshape(R * (M + 1), K, D)
        x = _run(self.visual, x, pad.transpose(1, 2).reshape(R * (M + 1), K), cfg.render_bf16)
        x = x.reshape(R, M + 1, K, D).transpose(1, 2)  # [R, K, M+1, D]
        # stage 2: along each epipolar line (query + M points), per view
        x = _run(self.epipolar, x.reshape(R * K, M + 1, D), pad.reshape(R * K, M + 1),
                 cfg.render_bf16).reshape(R, K, M + 1, D)
        q_k, h = x[:, :, :1], x[:, :, 1:]  # [R, K, 1, D], [R, K, M, D]
        a_logit = self.alpha_score(torch.cat([q_k.expand_as(h), h], -1))[..., 0]  # [R, K, M]
        alpha = _masked_softmax(a_logit, valid, dim=-1)
        f = (alpha[..., None] * h).sum(2)  # [R, K, D]
        # stage 3: across views with the query
        view_ok = valid.any(-1)  # [R, K]
        y = torch.cat([self.query_proj2(q_code)[:, None], self.view_proj(f)], 1)  # [R, 1+K, D]
        y = _run(self.view, y, torch.cat([torch.zeros_like(view_ok[:, :1]), ~view_ok], 1), cfg.render_bf16)
        q_s, g = y[:, :1], y[:, 1:]
        beta = _masked_softmax(self.beta_score(torch.cat([q_s.expand_as(g), g], -1))[..., 0], view_ok, dim=-1)  # [R, K]

        rgb_feat = torch.sigmoid(self.rgb_head((beta[..., None] * g).sum(1)))  # [R, 3]
        rgb_aux = (beta[..., None] * (alpha[..., None] * rgb).sum(2)).sum(1)  # [R, 3]
        depth = (beta * (alpha * (z if z.dim() == 1 else z[:, None])).sum(-1)).sum(-1)  # [R] expected z-depth
        main, aux = (rgb_feat, rgb_aux) if cfg.output == "features" else (rgb_aux, rgb_feat)
        out = {"rgb": main, "rgb_aux": aux, "rgb_blend": rgb_aux, "depth": depth, "alpha": alpha, "blend": beta,
               "valid": view_ok.any(-1)}
        if signals is not None:  # predict-then-blend with the colour weights: beta over views, alpha along rays
            sig = gather(signals.permute(0, 3, 1, 2).to(dtype), proj, "border").transpose(1, 2)  # [R, K, M, C]
            out["signal"] = (beta[..., None] * (alpha[..., None] * sig).sum(2)).sum(1)
        if colour_weights and cfg.output == "colors":  # rgb is the blend of the source colours
            out["colour_weights"] = (beta[..., None] * alpha).transpose(1, 2)  # [R, M, K]
            out["colour_depths"] = z.expand(R, M) if z.dim() == 1 else z  # [R, M]
        return out


def _masked_softmax(logits: Tensor, mask: Tensor, dim: int) -> Tensor:
    """Softmax over entries where ``mask``; all-masked rows give zeros."""
    logits = logits.masked_fill(~mask, -math.inf)
    out = torch.softmax(logits, dim=dim)
    return torch.nan_to_num(out, nan=0.0)
