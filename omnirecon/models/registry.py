"""Model presets by name: ``build_model("gpnr-tiny")``; every preset works on CPU and CUDA."""

from __future__ import annotations

import dataclasses

from omnirecon.errors import InputError


def _families():
    from omnirecon.models import (  # lazy: the model families import torch.nn and their configs; the registry is read by --help
        floor,
        gpnr,
        ibrnet,
        omnirecon,
    )

    return {
        "gpnr": (gpnr.GPNR, gpnr.GPNRConfig, gpnr.PRESETS),
        "ibrnet": (ibrnet.IBRNet, ibrnet.IBRNetConfig, ibrnet.PRESETS),
        "floor": (floor.PlaneSweep, floor.PlaneSweepConfig, floor.PRESETS),
        "omnirecon": (omnirecon.OmniRecon, omnirecon.OmniReconConfig, omnirecon.PRESETS),
    }


def preset_names() -> list[str]:
    return [name for _, _, presets in _families().values() for name in presets]


def family_of(preset: str) -> str:
    for fam, (_, _, presets) in _families().items():
        if preset in presets:
            return fam
    raise InputError(f"unknown model {preset!r}", None, f"use one of: {', '.join(preset_names())}")


def build_model(preset: str, overrides: dict | None = None):
    """A fresh model of preset ``preset`` with config fields replaced by ``overrides``."""
    cls, cfg_cls, presets = _families()[family_of(preset)]
    cfg = presets[preset]
    if overrides:
        names = {f.name for f in dataclasses.fields(cfg_cls)}
        unknown = set(overrides) - names
        if unknown:
            raise InputError(f"{preset} has no option {', '.join(sorted(unknown))}", None,
                             f"options are: {', '.join(sorted(names))}")
        cfg = dataclasses.replace(cfg, **{k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()})
    return cls(cfg)


def model_config_dict(model) -> dict:
    """The model's config as JSON-serialisable data."""
    return dataclasses.asdict(model.cfg)


RENDER_OPTIONS = {"render_samples": None, "render_bf16": False, "render_fine_pass": True, "render_coarse_samples": None,
                  "render_fine_samples": None}
"""Config fields that choose how a checkpoint renders outside training (measured per weights, e.g. the shipped
gpnr-tiny's 24 samples in bf16, omnirecon-tiny's coarse pass, ibrnet-tiny's fewer samples), at their full-render values."""


def full_render(model):
    """``model`` with every render option of its config at its full-render value (:data:`RENDER_OPTIONS`):
    what benchmarks compare levers and reference twins against. Returns ``model``."""
    names = {f.name for f in dataclasses.fields(model.cfg)}
    model.cfg = dataclasses.replace(model.cfg, **{k: v for k, v in RENDER_OPTIONS.items() if k in names})
    return model

