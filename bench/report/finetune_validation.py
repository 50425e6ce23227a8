"""BENCHMARKS.md section: Which views validate fine-tuning (`python -m bench finetune_validation`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import prov, read
from bench.report.finetune_levers import commit


def section(results: Path) -> str | None:
    """Held-out PSNR of the state `finetune` returns, per `--val-choice`."""
    r = read(results, "finetune_validation.json")
    if r is None:
        return None
    out = ["## Which views validate fine-tuning (`python -m bench finetune_validation`)", "",
           "`omnirecon finetune` returns the state with the best gain on its validation views (the start is a "
           "candidate), so it never lowers a scene's result only if those views behave like the held-out ones. "
           "`isolated`: the training views farthest from the other training views (the default); `spread`: evenly "
           "spaced. Each row: `finetune` at its defaults (`--nearest 6`, encoder + appearance at 5e-4; validation views "
           "stay sources of the other views and never blend their own photo), `--clock cpu --threads 1`; held-out PSNR "
           "in dB of the returned state, before -> after (objects: over the masks); the held-out views are only scored.",
           "", "| scene | validation views | CPU-s | whole image | objects | returned from | validation gain | load | commit |",
           "|---|---|---:|---|---|---:|---:|---:|---|"]
    for key, row in r["rows"].items():
        b, a = row["curve"][0], row["curve"][-1]
        obj = f"{b['psnr_masked']:.2f} -> {a['psnr_masked']:.2f}" if "psnr_masked" in b else "–"
        got = row["returned_from"]
        when = "start" if got["steps"] == 0 else f"{got['seconds']:g} s"
        out.append(f"| {key.split('/')[0]} | {row['val_choice']} {row['validation_views']} | {row['budget_s']:g} | "
                   f"{b['psnr']:.2f} -> {a['psnr']:.2f} ({a['psnr'] - b['psnr']:+.2f}) | {obj} | "
                   f"{when} | "
                   f"{got['val_gain']:+.2f} | {row['load_average']:.1f} | {commit(row)} |")
    out += ["", prov(r["provenance"])]
    return "\n".join(out)
