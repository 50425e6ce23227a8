"""BENCHMARKS.md section: Training of the shipped checkpoints (`python -m bench train_tiny`)."""

from __future__ import annotations

import json
from pathlib import Path

from bench.report.common import ROOT, prov


def section(results: Path) -> str | None:
    cards = [json.loads(p.read_text()) for p in sorted((ROOT / "checkpoints").glob("*/card.json"))]
    if not cards:
        return None
    out = ["## Training of the shipped checkpoints (`python -m bench train_tiny`)", "",
           "The same data, resolution and seed for every preset; budgets are process CPU seconds (other jobs on the "
           "machine do not shrink them) and differ where a run was continued (its stages, as commands, are in its "
           "model card). Training PSNR is over the sampled rays (half on foreground masks).", "",
           "| preset | budget (CPU s) | steps reached | CPU s used | wall s | threads | resolution | "
           "train PSNR first -> last log | stages |", "|---|---|---|---|---|---|---|---|---|"]
    for c in cards:
        parent = c.get("warm_start") or {}  # a warm start: its parent's stages come first
        first = (parent.get("curve") or {}).get("train") or [[0, c["train_psnr_first"]]]
        out.append(f"| {c['model']} | {c['cpu_budget_s']:.0f} | {c['steps']} | {c['cpu_seconds']:.0f} | "
                   f"{c['wall_seconds']:.0f} | {c['threads']} | {c['resolution']}²"
                   + (f", then {c['continued']['resolution']}² ({c['continued']['steps']} steps)" if c.get("continued")
                      else "") + " | "
                   f"{first[0][1]:.2f} -> {c['train_psnr_last']:.2f} | "
                   f"{len(parent.get('stages') or []) + len(c.get('stages', [1]))} |")
    weights = {c["model"]: c["data"]["weights"] for c in cards}
    same = all(w == weights[cards[0]["model"]] for w in weights.values())
    out += ["", "Data: " + ", ".join(cards[0]["data"]["procedural"] + cards[0]["data"]["real"])
            + (f" (weights {cards[0]['data']['weights']})" if same else
               " (weights " + "; ".join(f"{m} {w}" for m, w in weights.items()) + ")")
            + f"; held out: {cards[0]['held_out']}.", ""]
    warm = [c for c in cards if c.get("warm_start")]
    if warm:
        out += [" ".join(f"{c['model']} was warm-started from the checkpoint shipped before it (step "
                         f"{c['warm_start']['steps']}, {c['warm_start']['cpu_seconds']:.0f} CPU-s; data weights "
                         f"{(c['warm_start'].get('data') or {}).get('weights')}); its steps and CPU seconds are the sums."
                         for c in warm), ""]
    curves = [c["model"] for c in cards if (ROOT / "checkpoints" / c["model"] / "training_curve.png").is_file()]
    if curves:
        out += [" ".join(f"![{m} training curve](checkpoints/{m}/training_curve.png)" for m in curves), "",
                "Training curves (from each run's metrics.jsonl, drawn by `python -m bench train_tiny`): " + ", ".join(curves)
                + ". Validation is for monitoring only (the final step ships, never a selected one); its scenes are "
                "named in each metrics row: procedural seeds 901000 and 901001 (`VAL_SEEDS`) in rows the current code logs, "
                "900000 and 900001 (the first two synth:eval scenes) in rows logged by earlier code. Dashed line: a "
                "run resumed on a new (usually longer) schedule. Whether a continued run's final checkpoint replaces the one shipped "
                "before is decided on validation seeds 901000-901007 (K = 3 and 10), never on held-out scenes; the "
                "model cards give those numbers.", ""]
    for c in cards:
        out += [f"{c['model']}: " + prov(c["provenance"]), ""]
    return "\n".join(out)
