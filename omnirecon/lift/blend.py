"""Predict-then-blend (Omni-Recon §8) and the render-then-predict baseline.

Predict-then-blend: run a 2-D predictor on each of the K source views (maps ``p_i # [K, H, W, C]``),
then for every sample along a target ray sample the maps at the sample's projection into each view,
blend them with the model's own per-view colour weights and composite along the ray with its ray
weights, exactly as the model renders RGB (``render_rays(..., signals=p)``):

* Omni-Recon: ``omega`` of the appearance branch, then the SRDF volume weights ``w`` (final pass);
* IBRNet: the colour blend weights of the aggregator, then its volume weights (final pass);
* GPNR: ``beta_k alpha_km`` over views and epipolar samples (the weights of ``rgb_aux``).

The composite of a map is ``sum_s w_s sum_i omega_si p_i``; its total weight ``sum_s w_s`` (the ray's
opacity; 1 for GPNR wherever a view sees the ray) is measured by lifting a constant-one channel
alongside, and the lifted map is normalised by it: a constant map lifts to that constant, and
probabilities still sum to 1. Embeddings are blended, then L2-normalised. Pixels whose total weight
is below ``min_weight`` get uniform probabilities / zeros.

Render-then-predict: render the target's RGB with the same model and features, then run the
predictor on the render (GPNR: on ``rgb_aux``, the image made with the same weights; the feature head
``rgb`` is another option, ``rgb_key``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from omnirecon.lift.predictors import KINDS, Predictor


def supports_lifting(model) -> bool:
    """Whether ``model.render_rays`` takes ``signals`` (Omni-Recon, IBRNet, GPNR; not the plane-sweep floor)."""
    import inspect

    return "signals" in inspect.signature(model.render_rays).parameters


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
    key = rgb_key or ("rgb_aux" if "rgb_aux" in out else "rgb")
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
        rgb = out["rgb_aux" if "rgb_aux" in out else "rgb"]
    return predictor(rgb.float().cpu().clamp(0, 1))


def decode(maps: Tensor, kind: str) -> Tensor:
    """Class indices ``# [H, W]`` (argmax) for probabilities; the map itself otherwise."""
    return maps.argmax(-1) if kind == "probabilities" else maps
