"""What limits the gain of tuning on a scene: the same tuning run on the held-out test views themselves.

    python -m bench finetune_oracle --scene fern=../shared/data/llff/fern --mesh fern=MESH.ply --seconds 60

An oracle that never ships: ``omnirecon finetune``'s loop (same model, mesh, sources, resolution, pixels per
step, CPU clock, 1 thread) tunes on the held-out views' own pixels, with no validation views (the state at
each time is scored), with ``finetune``'s defaults (sources: each pixel's ``--nearest 6`` training views; what is
tuned: ``--tune``, ``--lr``; the row records them). Its test PSNR
is the most these tuned weights can give on those views in that time; beside the real run (tuned on the
training views, ``python -m bench finetune_curves``) and the blend ceiling (the best per-pixel convex blend of the source colours, ``python -m
bench finetune_ceiling``), it splits the missing gain in two: **generalisation** (oracle minus real: what
the training views do not teach about the held-out views) and **capacity** (ceiling minus oracle: per-pixel
blends that a network of the encoder's and appearance branch's form cannot produce in that time).

``--mode maps`` (one idea for that capacity; not shipped): the normal run (tuned on the training views,
the best state on validation views returned) with the encoder's output, the sources' feature maps
``F_i``, tuned directly as free parameters (with the appearance branch) instead of the encoder's weights:
a per-source texture of blend features, which carries to any view that sees the same source pixels, and
a step needs no encoder pass. Rows ``NAME:maps``. Results merge into ``bench/results/finetune_oracle.json``.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
TIMES = (0.0, 10.0, 30.0, 60.0)


MAPS_LR = 2e-3
"""Adam learning rate of the free feature maps (``--mode maps``; one guess, not swept)."""


def maps_tuner(cfg, s, g):
    """A :class:`~omnirecon.engine.tuning.Tuner` of the appearance branch plus the sources' encoded
    feature maps as free parameters (``--mode maps``)."""
    from omnirecon.engine.tuning import Tuner

    tuner = Tuner(cfg, s, g)  # cfg.tune = ("appearance",): the features are encoded once, in tuner.frozen
    maps = torch.nn.Parameter(tuner.frozen.maps.detach().clone())  # [K, C, h, w]
    tuner.frozen = replace(tuner.frozen, maps=maps)
    tuner.params.append(maps)
    tuner.start.append(maps.detach().clone())
    tuner.opt.add_param_group({"params": [maps], "lr": MAPS_LR})
    tuner.features = lambda: tuner.frozen  # validation and test scores use the tuned maps
    return tuner


def oracle(path: Path, mesh: Path, seconds: float, threads: int, mode: str = "oracle") -> dict:
    """The oracle's curve on one scene, or the ``maps`` run's (module docstring)."""
    from omnirecon.engine.machine import set_threads
    from omnirecon.engine.tuning import Tuner
    from omnirecon.workflows.finetune import VAL_PIXELS, FinetuneConfig, prepare, tune

    cfg = FinetuneConfig(ckpt=ROOT / "checkpoints" / "omnirecon-tiny", scene=path, mesh=mesh, seconds=seconds,
                         eval_at=tuple(t for t in TIMES if t <= seconds), clock="cpu", threads=threads,
                         max_held_out=4, val_views=0 if mode == "oracle" else 2,  # finetune's defaults otherwise
                         **({} if mode == "oracle" else {"tune": ("appearance",)}),  # maps: + the free feature maps
                         out=ROOT / "outputs" / "bench" / "finetune_oracle")
    set_threads(threads)
    s = prepare(cfg)
    g = torch.Generator().manual_seed(cfg.seed)
    if mode == "oracle":
        s = replace(s, train_px=[v for v in s.held_px if v.covered], val_px=[])  # tune on the test views' own pixels
        t = tune(cfg, s, Tuner(cfg, s, g), g, [], None)
    else:  # as run_finetune: validation pixels, the object share of them, the best state on validation
        val_idx = [torch.randperm(len(v.points), generator=g)[:VAL_PIXELS] for v in s.val_px]
        val_obj = None if s.scene.masks is None else [s.scene.masks[v.index].reshape(-1).bool()[v.pixels[i]]
                                                       for v, i in zip(s.val_px, val_idx)]
        t = tune(cfg, s, maps_tuner(cfg, s, g), g, val_idx, val_obj)
    keep = ("seconds", "steps", "psnr", "psnr_masked", "psnr_covered", "coverage", "val_psnr", "returned_from")
    return {"scene": str(path), "mesh": str(mesh), "mode": mode, "held_out": s.targets, "sources": s.views,
            "resolution": [s.scene.width, s.scene.height], "tuned": list(cfg.tune) + (["maps"] if mode == "maps" else []),
            "rays": cfg.rays, "lr": cfg.lr, "nearest": cfg.nearest, "visibility": cfg.visibility, "clock": cfg.clock, "threads": threads,
            "budget_s": seconds,
            "curve": [{k: c[k] for k in keep if k in c} for c in t.curve]}


def main(argv: list[str] | None = None) -> dict:
    from bench.finetune_levers import merge
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", action="append", required=True, help="NAME=PATH (repeatable)")
    p.add_argument("--mesh", action="append", required=True, help="NAME=MESH.ply, in the scene's input frame")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--mode", choices=("oracle", "maps"), default="oracle")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    meshes = dict(s.split("=", 1) for s in a.mesh)
    result = {}
    for name, path in (s.split("=", 1) for s in a.scene):
        started = provenance(seed=0)
        row = oracle(Path(path), Path(meshes[name]), a.seconds, a.threads, a.mode)
        print(name, a.mode, [(c["seconds"], round(c["psnr"], 2)) for c in row["curve"]])
        result = merge(a.out / "finetune_oracle.json", name if a.mode == "oracle" else f"{name}:maps", row, started)
    return result
