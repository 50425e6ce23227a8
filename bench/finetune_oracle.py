"""What limits the gain of tuning on a scene: the same tuning run on the held-out test views themselves.

    python -m bench finetune_oracle --scene fern=../shared/data/llff/fern --mesh fern=MESH.ply --seconds 60

An oracle that never ships: ``omnirecon finetune``'s loop (same model, mesh, sources, resolution, pixels per
step, CPU clock, 1 thread) tunes on the held-out views' own pixels, with no validation views (the state at
each time is scored). Its test PSNR is the most these tuned weights (encoder + appearance branch) can give
on those views in that time; beside the real run (tuned on the training views, ``python -m bench
finetune_curves``) and the blend ceiling (the best per-pixel convex blend of the source colours, ``python -m
bench finetune_ceiling``), it splits the missing gain in two: **generalisation** (oracle minus real: what
the training views do not teach about the held-out views) and **capacity** (ceiling minus oracle: per-pixel
blends that a network of the encoder's and appearance branch's form cannot produce in that time).
Results merge into ``bench/results/finetune_oracle.json``.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
TIMES = (0.0, 10.0, 30.0, 60.0)


def oracle(path: Path, mesh: Path, seconds: float, threads: int) -> dict:
    """The oracle's curve on one scene (module docstring)."""
    from omnirecon.engine.machine import set_threads
    from omnirecon.workflows.finetune import FinetuneConfig, Tuner, prepare, tune

    cfg = FinetuneConfig(ckpt=ROOT / "checkpoints" / "omnirecon-tiny", scene=path, mesh=mesh, seconds=seconds,
                         eval_at=tuple(t for t in TIMES if t <= seconds), clock="cpu", threads=threads,
                         max_held_out=4, val_views=0, out=ROOT / "outputs" / "bench" / "finetune_oracle")
    set_threads(threads)
    s = prepare(cfg)
    s = replace(s, train_px=[v for v in s.held_px if v.covered], val_px=[])  # tune on the test views' own pixels
    g = torch.Generator().manual_seed(cfg.seed)
    t = tune(cfg, s, Tuner(cfg, s, g), g, [], None)
    keep = ("seconds", "steps", "psnr", "psnr_masked", "psnr_covered", "coverage")
    return {"scene": str(path), "mesh": str(mesh), "held_out": s.targets, "sources": s.views,
            "resolution": [s.scene.width, s.scene.height], "tuned": list(cfg.tune), "rays": cfg.rays,
            "clock": cfg.clock, "threads": threads, "budget_s": seconds,
            "curve": [{k: c[k] for k in keep if k in c} for c in t.curve]}


def main(argv: list[str] | None = None) -> dict:
    from bench.finetune_levers import merge

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", action="append", required=True, help="NAME=PATH (repeatable)")
    p.add_argument("--mesh", action="append", required=True, help="NAME=MESH.ply, in the scene's input frame")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    meshes = dict(s.split("=", 1) for s in a.mesh)
    result = {}
    for name, path in (s.split("=", 1) for s in a.scene):
        row = oracle(Path(path), Path(meshes[name]), a.seconds, a.threads)
        print(name, [(c["seconds"], round(c["psnr"], 2)) for c in row["curve"]])
        result = merge(a.out / "finetune_oracle.json", name, row)
    return result
