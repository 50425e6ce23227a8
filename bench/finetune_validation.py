"""Which training views validate fine-tuning: held-out PSNR before -> after for each ``--val-choice``.

    python -m bench finetune_validation --scene demo=PATH --mesh demo=MESH.ply --seconds 30 --choices isolated spread

``omnirecon finetune`` returns the state with the best validation gain (the start is a candidate), so what it
returns is only as good as its validation views are like the held-out ones. Per scene and choice: ``finetune``
at its defaults (each pixel's ``--nearest 6`` sources, the encoder + appearance branch at 5e-4, 8192 pixels per
step, 2 validation views) but ``--val-choice``, ``--clock cpu --threads 1``, scored on the protocol's held-out
views at 0, 10 and ``--seconds`` s. The held-out views are only scored, never used to choose. Each row records
the validation views, the sources, which state was returned and its validation gain, and the held-out scores
(whole image; objects on scenes with masks) of the returned state. Rows merge into
``bench/results/finetune_validation.json`` under a file lock, keyed ``scene/choice/seconds``.
"""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
KEEP = ("seconds", "steps", "psnr", "psnr_masked", "psnr_covered", "coverage", "val_psnr", "val_psnr_masked",
        "returned_from")


def run_row(scene: str, path: Path, mesh: Path, choice: str, seconds: float, threads: int) -> dict:
    from omnirecon.workflows.finetune import FinetuneConfig, run_finetune

    work = ROOT / "outputs" / "bench" / "finetune_validation" / f"{scene}_{choice}_{seconds:g}"
    cfg = FinetuneConfig(ckpt=ROOT / "checkpoints" / "omnirecon-tiny", scene=path, mesh=mesh, seconds=seconds,
                         eval_at=(0.0, 10.0, seconds), clock="cpu", threads=threads, out=work, max_held_out=4,
                         val_choice=choice)
    ft = run_finetune(cfg)
    first, last = ft["curve"][0], ft["curve"][-1]
    return {"scene": str(path), "mesh": str(mesh), "val_choice": choice, "validation_views": ft["validation_views"],
            "sources": ft["sources"], "held_out": ft["held_out"], "nearest": cfg.nearest, "tuned": ft["tuned"],
            "lr": ft["lr"], "rays": ft["rays"], "val_margin": ft["val_margin"], "val_guard": ft["val_guard"],
            "scored_by": ft["scored_by"], "budget_s": seconds, "clock": ft["clock"], "threads": threads,
            "resolution": ft["resolution"], "returned_from": ft["returned_from"],
            "curve": [{k: c[k] for k in KEEP if k in c} for c in ft["curve"]],
            "gain_db": last["psnr"] - first["psnr"],
            **({"gain_masked_db": last["psnr_masked"] - first["psnr_masked"]} if "psnr_masked" in last else {}),
            "load_average": os.getloadavg()[0]}


def main(argv: list[str] | None = None) -> dict:
    from bench.finetune_levers import merge, scene_parser, scenes_and_meshes
    from omnirecon.provenance import provenance

    p = scene_parser(__doc__)
    p.add_argument("--choices", nargs="+", default=["isolated", "spread"], choices=["isolated", "spread"])
    p.add_argument("--seconds", type=float, default=30.0)
    a = p.parse_args(argv)
    result = {}
    for name, path, mesh in scenes_and_meshes(a):
        for choice in a.choices:
            started = provenance(seed=0)
            r = run_row(name, path, mesh, choice, a.seconds, a.threads)
            c0, c1 = r["curve"][0], r["curve"][-1]
            print(name, choice, r["validation_views"], f"{c0['psnr']:.2f} -> {c1['psnr']:.2f} dB,",
                  f"returned from {r['returned_from']['seconds']:g} s (validation {r['returned_from']['val_gain']:+.2f})")
            result = merge(a.out / "finetune_validation.json", f"{name}/{choice}/{a.seconds:g}", r, started)
    return result
