"""Parameter-efficient tuning (PET) of Omni-Recon's appearance branch for lifted semantics (spec §8, PET).

Only the appearance branch (``model.appearance``: ``proj`` and the three Linears of ``mlp``) decides
how per-view maps are blended (``omega``); the geometry branch, the encoder and the ray weights stay
frozen, as do the base weights of the tuned layers. Modes:

* ``lora``: ``W x + (alpha / r) B A x`` on every appearance Linear, ``A # [r, in]`` Kaiming-uniform,
  ``B # [out, r]`` zero, so the tuned model starts exactly equal to the base model;
* ``bias``: only the biases of the appearance Linears (BitFit);
* ``full``: every appearance parameter (a reference point, not parameter-efficient).

**Supervision: leave-one-out lifting.** A few labelled views (ground-truth labels); for each, the
one-hot labels of the ``K`` nearest *other* labelled views are lifted onto it through the model
(volumetric path, :meth:`OmniRecon.render_rays` with ``signals``), normalised to probabilities, and
the cross-entropy to its own labels is minimised over random rays. Gradients reach only ``omega``.
Evaluation: mIoU of labels lifted from the labelled views to held-out targets, before and after.

Adapters save as a small safetensors file (:func:`save_adapters`; the trainable tensors and the
mode/rank/alpha as metadata) and load onto a base model with :func:`load_adapters`. The fused mesh
renderer reads the appearance weights directly: call :func:`merge_lora` (or tune in ``bias`` mode)
before building a ``MeshRenderer``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omnirecon.data.io import atomic_path
from omnirecon.engine.views import select_sources
from omnirecon.errors import InputError
from omnirecon.lift import metrics as M
from omnirecon.lift.blend import render_lifted
from omnirecon.lift.predictors import labels_to_classes
from omnirecon.options import AdamRate, Seeded, SourceViews, StepRays, Steps, command_defaults
from omnirecon.rays import Rays, Sources

Mode = Literal["lora", "bias", "full"]


class LoRALinear(nn.Module):
    """A frozen ``nn.Linear`` plus a low-rank update: ``base(x) + (alpha / rank) * B(A(x))``."""

    def __init__(self, base: nn.Linear, rank: int, alpha: float | None = None):
        super().__init__()
        if rank < 1:
            raise ValueError(f"LoRA rank must be at least 1, got {rank}")
        self.base = base
        for p in base.parameters():
            p.requires_grad_(False)
        kw = dict(dtype=base.weight.dtype, device=base.weight.device)
        self.lora_A = nn.Parameter(torch.empty(rank, base.in_features, **kw))
        """Down-projection. ``# [r, in]``"""
        self.lora_B = nn.Parameter(torch.zeros(base.out_features, rank, **kw))
        """Up-projection, zero at the start. ``# [out, r]``"""
        nn.init.kaiming_uniform_(self.lora_A, a=math.sqrt(5))
        self.rank = rank
        self.scale = (rank if alpha is None else alpha) / rank

    def forward(self, x: Tensor) -> Tensor:
        return self.base(x) + F.linear(F.linear(x, self.lora_A), self.lora_B) * self.scale

    def merged(self) -> nn.Linear:
        """A plain ``nn.Linear`` with ``W + scale * B A`` (frozen like the base)."""
        out = nn.Linear(self.base.in_features, self.base.out_features, bias=self.base.bias is not None,
                        dtype=self.base.weight.dtype, device=self.base.weight.device)
        with torch.no_grad():
            out.weight.copy_(self.base.weight + self.scale * self.lora_B @ self.lora_A)
            if self.base.bias is not None:
                out.bias.copy_(self.base.bias)
        return out.requires_grad_(False)


def _appearance_linears(model) -> list[tuple[nn.Module, str]]:
    """(parent, attribute) of every Linear of the appearance branch: ``proj`` and the ``mlp`` entries."""
    app = model.appearance if model.capabilities.appearance else None
    if app is None or not hasattr(app, "mlp"):
        raise ValueError(f"{type(model).__name__} has no decoupled appearance branch (Omni-Recon only)")
    return [(app, "proj")] + [(app.mlp, str(i)) for i, m in enumerate(app.mlp) if isinstance(m, (nn.Linear, LoRALinear))]


def prepare(model, mode: Mode, rank: int = 4, alpha: float | None = None) -> list[nn.Parameter]:
    """Freeze ``model`` and make the ``mode``'s parameters trainable (adding LoRA adapters in place for
    ``lora``). Returns the trainable parameters."""
    targets = _appearance_linears(model)
    for p in model.parameters():
        p.requires_grad_(False)
    if mode == "lora":
        for parent, name in targets:
            layer = getattr(parent, name)
            if not isinstance(layer, LoRALinear):
                setattr(parent, name, LoRALinear(layer, rank, alpha))
        return [p for parent, name in targets for p in (getattr(parent, name).lora_A, getattr(parent, name).lora_B)]
    if any(isinstance(getattr(parent, name), LoRALinear) for parent, name in targets):
        raise ValueError("the model already carries LoRA adapters; merge them first (merge_lora)")
    if mode == "bias":
        params = [getattr(parent, name).bias for parent, name in targets]
    elif mode == "full":
        params = list(model.appearance.parameters())
    else:
        raise ValueError(f"mode must be lora, bias or full, got {mode!r}")
    for p in params:
        p.requires_grad_(True)
    return params


def merge_lora(model):
    """Replace every :class:`LoRALinear` of the appearance branch by its merged ``nn.Linear`` (in place)."""
    for parent, name in _appearance_linears(model):
        layer = getattr(parent, name)
        if isinstance(layer, LoRALinear):
            setattr(parent, name, layer.merged())
    return model


def trainable(model) -> dict[str, Tensor]:
    """The parameters that require gradients, by name."""
    return {n: p for n, p in model.named_parameters() if p.requires_grad}


# ---------------------------------------------------------------------- leave-one-out supervision
@dataclass
@command_defaults(steps=40, lr=1e-2)
class PETOptions(Seeded, SourceViews, Steps, AdamRate, StepRays):
    """How to tune."""

    mode: Mode = "lora"
    """lora (low-rank adapters), bias (biases only) or full (all appearance parameters, a reference)."""
    rank: int = 4
    """LoRA rank r."""
    alpha: float | None = None
    """LoRA scale numerator (update scaled by alpha / r; default r, i.e. 1)."""
    min_weight: float = 0.05
    """Rays whose total blend weight (opacity) is below this are not supervised."""


@dataclass
class LabelledView:
    """One labelled view and the leave-one-out lift onto it."""

    view: int
    """Scene view index."""
    sources: list[int]
    """The other labelled views lifted onto it."""
    features: object
    """``model.encode`` of ``sources`` (frozen encoder: computed once)."""
    rays: object
    """Every pixel ray of the view (:class:`omnirecon.models.base.Rays`)."""
    classes: Tensor
    """Ground-truth class index per pixel, -1 unknown. ``# [H W]`` int64"""
    signals: Tensor
    """A constant-one channel and the sources' one-hot labels. ``# [K, H, W, 1 + C]``"""
    pixels: Tensor
    """Pixels with a known class. ``# [P]`` int64"""


def one_hot_views(scene, views: list[int], table: np.ndarray) -> Tensor:
    """One-hot ground-truth labels of ``views`` (channels: ``table``; unknown values: all zero). ``# [K, H, W, C]``"""

    cls = labels_to_classes(scene.labels[views], table)  # [K, H, W]
    out = np.zeros((*cls.shape, len(table)), np.float32)
    ok = cls >= 0
    out[ok, cls[ok]] = 1.0
    return torch.from_numpy(out)


def labelled_views(model, scene, labelled: list[int], table: np.ndarray, num_views: int) -> list[LabelledView]:
    """The leave-one-out setup of every labelled view (its ``num_views`` nearest other labelled views)."""

    if len(labelled) < 2:
        raise ValueError("leave-one-out supervision needs at least 2 labelled views")
    dtype = next(model.parameters()).dtype
    out = []
    for v in labelled:
        others = [u for u in labelled if u != v]
        src = select_sources(scene, scene.cameras[v], others, min(num_views, len(others)))
        with torch.no_grad():
            feats = model.encode(_sources(scene, src, dtype))
        onehot = one_hot_views(scene, src, table)
        signals = torch.cat([torch.ones(*onehot.shape[:3], 1), onehot], -1).to(dtype)
        cls = torch.from_numpy(labels_to_classes(scene.labels[v], table).reshape(-1))
        rays = Rays.from_image(scene.cameras[[v]].to(dtype=dtype))
        out.append(LabelledView(v, src, feats, rays, cls, signals, (cls >= 0).nonzero()[:, 0]))
    return out


def _sources(scene, views, dtype):

    s = Sources.from_scene(scene, views)
    b = None if s.bounds is None else s.bounds.to(dtype)
    return Sources(s.images.to(dtype), s.cameras.to(dtype=dtype), s.near, s.far, s.rig, b)


def semantic_loss(model, lv: LabelledView, idx: Tensor, min_weight: float = 0.05) -> Tensor:
    """Cross-entropy of the leave-one-out lifted probabilities at pixels ``idx`` of ``lv`` (rays whose blend
    weight is at least ``min_weight``; 0 when none is)."""
    out = model.render_rays(lv.features, lv.rays[idx], signals=lv.signals)
    sig = out["signal"]  # [R, 1 + C]
    weight, lifted = sig[:, 0], sig[:, 1:]
    probs = lifted / lifted.sum(-1, keepdim=True).clamp_min(1e-12)
    cls = lv.classes[idx]
    ok = (weight >= min_weight) & (cls >= 0)
    if not ok.any():
        return sig.sum() * 0
    p = probs[ok].gather(1, cls[ok][:, None])[:, 0]
    return -(p.clamp_min(1e-6).log()).mean()


def full_loss(model, views: list[LabelledView], min_weight: float = 0.05, chunk: int = 1024) -> float:
    """:func:`semantic_loss` over every known pixel of every labelled view (no gradients)."""
    total, count = 0.0, 0
    with torch.no_grad():
        for lv in views:
            for s in range(0, len(lv.pixels), chunk):
                idx = lv.pixels[s:s + chunk]
                total += float(semantic_loss(model, lv, idx, min_weight)) * len(idx)
                count += len(idx)
    return total / max(count, 1)


def tune(model, views: list[LabelledView], options: PETOptions) -> dict:
    """Prepare ``model`` for ``options.mode`` and run ``options.steps`` Adam steps on the leave-one-out
    cross-entropy. Returns ``{"params": n, "losses": [...]}``; the model is tuned in place."""
    torch.manual_seed(options.seed)
    params = prepare(model, options.mode, options.rank, options.alpha)
    opt = torch.optim.Adam(params, lr=options.lr)
    g = torch.Generator().manual_seed(options.seed)
    losses = []
    model.eval()
    for step in range(options.steps):
        lv = views[step % len(views)]
        idx = lv.pixels[torch.randint(len(lv.pixels), (options.rays,), generator=g)]
        loss = semantic_loss(model, lv, idx, options.min_weight)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return {"params": int(sum(p.numel() for p in params)), "losses": losses}


def lifted_miou(model, scene, targets: list[int], labelled: list[int], table: np.ndarray, num_views: int,
                maps_of=None, chunk: int = 4096) -> dict:
    """mIoU (in %) of the labelled views' labels lifted to each of ``targets`` (its ``num_views`` nearest
    labelled views; ``maps_of(views) -> [K, H, W, C]``, default their one-hot ground truth), per target and mean."""

    dtype = next(model.parameters()).dtype
    maps_of = maps_of or (lambda views: one_hot_views(scene, views, table))
    per = []
    for t in targets:
        src = select_sources(scene, scene.cameras[t], labelled, num_views)
        with torch.no_grad():
            feats = model.encode(_sources(scene, src, dtype))
            lifted = render_lifted(model, feats, scene.cameras[t], {"l": (maps_of(src), "probabilities")}, chunk)
        gt = labels_to_classes(scene.labels[t], table)
        per.append(100 * M.iou_from_confusion(M.confusion(lifted.maps["l"].argmax(-1), gt, len(table)))["miou"])
    return {"miou": float(np.mean(per)) if per else float("nan"), "per_target": per}


# ---------------------------------------------------------------------- files
def save_adapters(model, path: Path, options: PETOptions) -> Path:
    """Write the trainable tensors of ``model`` (adapters or tuned biases) and the mode to a safetensors file."""
    from safetensors.torch import save_file

    tensors = {n: p.detach().contiguous().cpu() for n, p in trainable(model).items()}
    if not tensors:
        raise ValueError("the model has no trainable parameters: call prepare() or tune() first")
    meta = {"mode": options.mode, "rank": str(options.rank), "alpha": str(options.alpha or options.rank)}
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata=meta)
    return Path(path)


def load_adapters(model, path: Path):
    """Load a :func:`save_adapters` file onto a base ``model`` (adding LoRA layers for ``lora``), in place."""
    from safetensors import safe_open

    path = Path(path)
    if not path.is_file():
        raise InputError("adapter file not found", path, "pass a file written by `omnirecon pet`")
    with safe_open(str(path), "pt") as f:
        meta = f.metadata() or {}
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    if meta.get("mode") not in ("lora", "bias", "full"):
        raise InputError("not an adapter file (no mode in its metadata)", path, "pass a file written by `omnirecon pet`")
    prepare(model, meta["mode"], int(meta.get("rank", 4)), float(meta.get("alpha", meta.get("rank", 4))))
    own = dict(model.named_parameters())
    missing = [k for k in tensors if k not in own]
    if missing:
        raise InputError(f"adapter tensors {missing[:3]} do not match the model", path, "use the same model preset")
    with torch.no_grad():
        for k, v in tensors.items():
            own[k].copy_(v)
    return model
