"""Predict-then-blend (Omni-Recon §8) and the render-then-predict baseline.

Predict-then-blend: run a 2-D predictor on each of the K source views (maps ``p_i # [K, H, W, C]``),
then for every sample along a target ray sample the maps at the sample's projection into each view,
blend them with the model's own per-view colour weights and composite along the ray with its ray
weights, exactly as the model renders RGB (``render_rays(..., signals=p)``):

* Omni-Recon: ``omega`` of the appearance branch, then the SRDF volume weights ``w`` (final pass);
* IBRNet: the colour blend weights of the aggregator, then its volume weights (final pass);
* GPNR: ``beta_k alpha_km`` over views and epipolar samples (the weights of ``rgb_blend``, the blended source colours).

The composite of a map is ``sum_s w_s sum_i omega_si p_i``; its total weight ``sum_s w_s`` (the ray's
opacity; 1 for GPNR wherever a view sees the ray) is measured by lifting a constant-one channel
alongside, and the lifted map is normalised by it: a constant map lifts to that constant, and
probabilities still sum to 1. Embeddings are blended, then L2-normalised. Pixels whose total weight
is below ``min_weight`` get uniform probabilities / zeros.

**Mesh path** (Omni-Recon only, :func:`render_lifted_mesh`, :func:`lift_mesh_view`): rasterize a baked
mesh at the target (``omnirecon.mesh.ibr.MeshRenderer``), one surface point per pixel, and blend
the maps there with the appearance branch's ``omega``: no ray weights, so a covered pixel has weight 1
and a pixel no triangle covers weight 0. :func:`lift_points` blends at arbitrary surface points (face
centroids, for labelling a mesh's faces).

Render-then-predict: render the target's RGB with the same model and features, then run the
predictor on the render (GPNR: on ``rgb_blend``, the image made with the same weights, whichever head
its ``output`` makes ``rgb``; the feature head is another option, ``rgb_key``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from omnirecon.lift.predictors import KINDS, Predictor
from omnirecon.mesh.shader import ShadeResult


def supports_lifting(model) -> bool:
    """Whether ``model.render_rays`` takes ``signals`` (Omni-Recon, IBRNet, GPNR; not the plane-sweep floor)."""
    return model.capabilities.signals


def normalise(lifted: Tensor, weight: Tensor, kind: str, min_weight: float = 1e-4) -> Tensor:
    """Normalise a composited map ``lifted # [..., C]`` with total weight ``weight # [...]`` by ``kind``."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    ok = (weight > min_weight)[..., None]
    if kind == "embedding":
        return torch.nn.functional.normalize(lifted, dim=-1) * ok
    if kind == "probabilities":
        total = lifted.sum(-1, keepdim=True)
        uniform = torch.full_like(lifted, 1.0 / lifted.shape[-1])
        return torch.where(ok & (total > 0), lifted / total.clamp_min(1e-12), uniform)
    return torch.where(ok, lifted / weight.clamp_min(1e-12)[..., None], torch.zeros_like(lifted))


@dataclass
class Lifted:
    """What one lifting render gives."""

    maps: dict[str, Tensor]
    """Normalised lifted map per signal name. ``# [H, W, C]`` each"""
    weight: Tensor
    """Total blend weight per pixel (opacity for volumetric models). ``# [H, W]``"""
    rgb: Tensor
    """The model's render of the same pixels (``rgb_key``), for render-then-predict. ``# [H, W, 3]``"""
    outputs: dict[str, Tensor]
    """All other outputs of ``render_view`` (depth, acc, ...)."""


def render_lifted(model, features, camera, signals: dict[str, tuple[Tensor, str]], chunk: int = 4096,
                  rgb_key: str | None = None, min_weight: float = 1e-4) -> Lifted:
    """Lift several maps in one render: ``signals = {name: (maps # [K, H, W, C], kind)}`` with the K source
    views in the order of ``features``. Returns normalised ``[H, W, C]`` maps, the weight and the RGB."""
    if not supports_lifting(model):
        raise ValueError(f"{type(model).__name__} does not support lifting (its render_rays takes no signals)")
    names = list(signals)
    parts = [signals[n][0].float() for n in names]
    K, H, W = parts[0].shape[:3] if parts else (0, 0, 0)
    for n, p in zip(names, parts):
        if p.dim() != 4 or p.shape[:3] != (K, H, W):
            raise ValueError(f"signal {n!r} must be [K, H, W, C] like the others, got {list(p.shape)}")
    src = features.sources.images
    if parts and (K, H, W) != tuple(src.shape[:3]):
        raise ValueError(f"signals are [{K}, {H}, {W}, C] but the sources are {list(src.shape[:3])}")
    ones = torch.ones(*src.shape[:3], 1)
    stacked = torch.cat([ones, *parts], -1).to(device=src.device, dtype=src.dtype)
    camera = camera.to(device=src.device, dtype=src.dtype)
    out = model.render_view(features, camera, chunk=chunk, signals=stacked)
    sig = out.pop("signal").float().cpu()
    weight = sig[..., 0]
    maps, c = {}, 1
    for n, p in zip(names, parts):
        maps[n] = normalise(sig[..., c:c + p.shape[-1]], weight, signals[n][1], min_weight)
        c += p.shape[-1]
    key = rgb_key or ("rgb_blend" if "rgb_blend" in out else "rgb")
    rgb = out[key].float().cpu().clamp(0, 1)
    return Lifted(maps, weight, rgb, {k: v.cpu() for k, v in out.items()})


def lift_view(model, features, camera, signals: Tensor, kind: str, chunk: int = 4096) -> Tensor:
    """Predict-then-blend one target view: ``signals # [K, H, W, C]`` (per source view) -> ``# [H, W, C]``
    (probabilities re-normalised to sum 1, embeddings L2-normalised, regression weight-normalised)."""
    return render_lifted(model, features, camera, {"signal": (signals, kind)}, chunk).maps["signal"]


def predict_then_blend(model, features, camera, predictor: Predictor, source_views: list[int] | None = None,
                       chunk: int = 4096) -> Tensor:
    """Run ``predictor`` on every source image of ``features`` (scene views ``source_views`` for oracles)
    and lift the maps to ``camera``. ``# [H, W, C]``"""
    maps = predictor.predict_views(features.sources.images.cpu(), source_views)
    return lift_view(model, features, camera, maps, predictor.kind, chunk)


def render_then_predict(model, features, camera, predictor: Predictor, chunk: int = 4096,
                        rgb: Tensor | None = None) -> Tensor:
    """The baseline: render the target RGB (or take ``rgb # [H, W, 3]``), then run ``predictor`` on it."""
    if rgb is None:
        src = features.sources.images
        out = model.render_view(features, camera.to(device=src.device, dtype=src.dtype), chunk=chunk)
        rgb = out["rgb_blend" if "rgb_blend" in out else "rgb"]
    return predictor(rgb.float().cpu().clamp(0, 1))


def decode(maps: Tensor, kind: str) -> Tensor:
    """Class indices ``# [H, W]`` (argmax) for probabilities; the map itself otherwise."""
    return maps.argmax(-1) if kind == "probabilities" else maps


# ---------------------------------------------------------------------- mesh path (Omni-Recon §7)
def _check_mesh_signal(renderer, name: str, p: Tensor) -> None:
    if p.dim() != 4 or p.shape[0] != renderer.num_views:
        raise ValueError(f"signal {name!r} must be [K={renderer.num_views}, H, W, C], got {list(p.shape)}")


def render_lifted_mesh(renderer, camera, signals: dict[str, tuple[Tensor, str]], min_weight: float = 1e-4) -> Lifted:
    """Predict-then-blend through a baked mesh: one surface point per pixel (rasterized at ``camera``), each
    map ``# [K, H', W', C]`` (any resolution covering the sources) sampled at the point's projection into
    every source and blended with the appearance branch's ``omega`` (``renderer``: a
    :class:`~omnirecon.mesh.ibr.MeshRenderer`). There is no ray weight: a covered pixel has weight
    1, a pixel no triangle covers weight 0 (uniform probabilities, zero embeddings and regression, as
    :func:`normalise`). ``rgb`` is the mesh path's render (the renderer's background where uncovered);
    ``outputs`` hold ``depth``, ``mask`` (covered) and ``seen`` (some source sees the point)."""
    for n, (p, _) in signals.items():
        _check_mesh_signal(renderer, n, p)
    with torch.inference_mode():
        shaded = renderer.weights(camera, with_rgb=True, with_coords=True)
        surf = shaded.surface
        covered = torch.ones(len(surf.pixels), 1, dtype=renderer.dtype, device=renderer.device)  # [P, 1]
        weight = surf.image(covered, 0.0)[..., 0].float().cpu()  # [H, W]
        maps = {}
        for n, (p, kind) in signals.items():
            values = renderer.blend(shaded, p.to(renderer.device, renderer.dtype).permute(0, 3, 1, 2))  # [P, C]
            maps[n] = normalise(surf.image(values, 0.0).float().cpu(), weight, kind, min_weight)  # [H, W, C]
        bg = torch.tensor(renderer.options.background, dtype=renderer.dtype, device=renderer.device)
        rgb = surf.image(shaded.rgb, bg).float().cpu().clamp(0, 1)  # [H, W, 3]
        outputs = {"depth": surf.image(surf.depth[:, None].to(renderer.dtype), 0.0)[..., 0].float().cpu(),
                   "mask": weight > 0,
                   "seen": surf.image(shaded.mask.any(0)[:, None].to(renderer.dtype), 0.0)[..., 0].cpu() > 0}
    return Lifted(maps, weight, rgb, outputs)


def lift_mesh_view(renderer, camera, signals: Tensor, kind: str) -> Tensor:
    """Predict-then-blend one target view through the mesh (:func:`render_lifted_mesh`): ``signals #
    [K, H', W', C]`` -> ``# [H, W, C]`` (probabilities sum to 1, embeddings L2-normalised)."""
    return render_lifted_mesh(renderer, camera, {"signal": (signals, kind)}).maps["signal"]


def lift_points(renderer, points: Tensor, origins: Tensor, signals: Tensor, kind: str, chunk: int = 8192,
                min_weight: float = 1e-4, depths: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Blend per-view maps ``signals # [K, H', W', C]`` at arbitrary surface ``points # [P, 3]`` seen from
    ``origins # [P, 3]`` (e.g. face centroids, each seen from in front of its face) with the appearance
    branch (``model.shade``), masking the sources the renderer's projection rules out (behind, outside the
    image and, with ``MeshRenderOptions(visibility=True)``, occluded). ``depths # [K, H, W]`` (the sources'
    rasterized z-depth, 0 = background; e.g. ``renderer.source_depths()``) adds a strict test: a source
    is also masked where the point lies more than ``visibility_tol`` behind the surface at its *nearest*
    pixel (the renderer's own test takes the farthest of four, so it keeps points just behind an
    occluder's silhouette). Returns the normalised maps ``# [P, C]`` and ``seen # [P]`` (some source sees
    the point; the others get weight 0)."""

    _check_mesh_signal(renderer, "signals", signals)
    cams = renderer.sources.cameras
    size = torch.tensor([cams.width, cams.height], dtype=renderer.dtype, device=renderer.device)[None, :, None]
    sig = signals.to(renderer.device, renderer.dtype).permute(0, 3, 1, 2)  # [K, C, H', W']
    if depths is not None:
        d = depths.to(renderer.device, renderer.dtype)
        far = torch.where(d > 0, d, torch.full_like(d, float("inf"))).reshape(-1)  # [K H W]
        offset = torch.arange(len(d), device=renderer.device)[:, None] * d.shape[1] * d.shape[2]  # [K, 1]
    outs, seen = [], []
    with torch.inference_mode():
        for s in range(0, len(points), chunk):
            p = points[s:s + chunk].to(renderer.device, renderer.dtype)  # [n, 3]
            o = origins[s:s + chunk].to(renderer.device, renderer.dtype)
            uv, z, mask = renderer.project(p.T.contiguous())  # [K, 2, n], [K, n], [K, n]
            if depths is not None:
                col = uv[:, 0].floor().clamp(0, cams.width - 1).long()  # [K, n]
                row = uv[:, 1].floor().clamp(0, cams.height - 1).long()
                mask = mask & (z <= far[offset + row * cams.width + col] * (1 + renderer.options.visibility_tol))
            omega = renderer.model.shade(renderer.features, p, o, visible=mask.T)["blend"].T  # [K, n]
            values = renderer.blend(ShadeResult(None, omega, mask, uv / size), sig)  # [n, C]
            outs.append(values.float().cpu())
            seen.append(mask.any(0).cpu())
    seen_all = torch.cat(seen) if seen else torch.zeros(0, dtype=torch.bool)
    values = torch.cat(outs) if outs else torch.zeros(0, signals.shape[-1])
    return normalise(values, seen_all.float(), kind, min_weight), seen_all
