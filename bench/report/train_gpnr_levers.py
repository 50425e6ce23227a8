"""BENCHMARKS.md section: gpnr-tiny's DTU aspect and wider-pool levers (`python -m bench train_gpnr_levers`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import prov
from bench.report.train_background import probe_columns, psnr_rows

GROUPS = {"real": "mean: real scenes, held-out views", "black": "mean: lego and chair on black",
          "validation": "mean: every real validation row", "procedural": "mean: procedural validation seeds",
          "procedural 4:3": "mean: procedural validation seeds at 4:3",
          "all procedural": "mean: procedural seeds, square and 4:3"}


def section(results: Path) -> str | None:
    """The levers' arms against their control, per budget; None before a run."""
    got = probe_columns(results, "train_gpnr_levers.json", "control", control_first=True)
    if got is None:
        return None
    r, probes, cols = got
    s, shipped = r["settings"], r.get("shipped")
    head = (["scene"] + ([f"shipped gpnr-tiny (step {shipped['step']})"] if shipped else [])
            + [f"{arm}, {budget} CPU-s" for budget, arm, _, _ in cols])
    lines = ["### DTU's aspect and a wider source pool (`python -m bench train_gpnr_levers`)", "",
             "The two levers of gpnr-tiny's DTU deficit issue 47 names that the sections above had not tried, probed "
             "on validation data: each arm continues checkpoints/gpnr-tiny (`--init`, fresh optimizer, constant lr "
             f"{s['lr']:g} after {s['warmup']} warm-up steps) for the same process-CPU budget (1 thread, seed 0) on "
             f"the control's data mix of the section above (procedural rigs at weight 2 with {s['synth_scenes']} "
             "scenes each, the same seeds in every arm, passed as folders; the real training scenes at 1, on white), "
             f"K drawn from [{s['num_views_range'][0]}, {s['num_views_range'][1]}], a new scene every step. "
             "`control`: square procedural scenes, each step's K sources from the target's 2K nearest views (as "
             f"shipped); `aspect`: the same procedural scenes at DTU's 4:3 (`omnirecon synth --aspect {s['aspect']:g}`: "
             "the square images' middle rows, the same horizontal field of view); `pool`: the K sources from the "
             f"target's {s['pool']} nearest views (`--pool {s['pool']}`, wider baselines, as DTU's protocol sources "
             "lie far from its targets). Scored as the section above (the `cpu` protocol's targets and sources, 64 "
             f"px, K = {s['num_views']}, mean PSNR over the targets, whole image, dB; in brackets the change against "
             "the control of the same budget), plus the procedural validation seeds rendered at 4:3. Validation only: "
             "fern, dtu_scan24/37 and the evaluation seeds are not looked at.", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += psnr_rows(r, shipped, cols, GROUPS)
    lines.append("| " + " | ".join(["steps"] + (["-"] if shipped else []) + [str(v["steps"]) for _, _, v, _ in cols])
                 + " |")
    lines += [""] + [f"{budget} CPU-s per arm: {probe['verdict']}." for budget, probe in probes]
    arms = probes[-1][1]["arms"]
    lines += ["", f"Scoring: about {next(iter(arms.values()))['eval_cpu_s']:.0f} CPU-s per checkpoint. Commands: "
              + "; ".join(f"{arm}: `{v['command']}`" for arm, v in arms.items()) + ".", ""]
    return "\n".join(lines + [prov(p["provenance"]) + f" ({b} CPU-s probe)" for b, p in probes] + [""])
