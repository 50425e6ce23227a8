"""GPNR ablations in the seed's form, at the tiny budget: each row trained with the same data,
seed and CPU budget, then scored on the held-out procedural scenes.

    python -m bench ablation_gpnr --cpu-budget 900          # the four rows of the seed's Table 3
    python -m bench ablation_gpnr --tiny                    # a fast smoke run (tests; numbers mean nothing)

Rows: full model; without the visual (stage-1) transformer; without ray canonicalisation; without
coordinate canonicalisation. The colour-vs-feature comparison comes from every row at once: GPNR
trains both heads, and each row reports ``rgb`` (feature head) and ``rgb_aux`` (blended source
colours). Writes ``bench/results/ablation_gpnr.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from bench import train_tiny
from omnirecon.data.io import write_json
from omnirecon.provenance import provenance

ROWS = {
    "full": [],
    "no visual transformer": ["visual_transformer=false"],
    "no ray canonicalization": ["canonical_rays=false"],
    "no coordinate canonicalization": ["canonical_coords=false"],
}
K = 5
"""Source views at evaluation: the tiny preset's training K."""


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cpu-budget", type=float, default=900.0)
    p.add_argument("--steps", type=int, default=750, help="learning-rate schedule length")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--rows", nargs="+", default=list(ROWS))
    p.add_argument("--tiny", action="store_true")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "ablation_gpnr.json")
    a = p.parse_args(argv)
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.engine.evaluate import evaluate

    if not a.tiny:
        train_tiny.prepare(32)
    result = {"provenance": provenance(seed=train_tiny.SEED), "cpu_budget_s": a.cpu_budget, "steps": a.steps,
              "num_views": K, "tiny": a.tiny, "rows": {}}
    for row in a.rows:
        overrides = ROWS[row] + (["num_samples=8", "dim=32", "mlp_dim=32", "layers=[1,1,1]"] if a.tiny else [])
        name = "ablation_" + row.replace(" ", "_") + ("_tiny" if a.tiny else "")
        run = train_tiny.train("gpnr-tiny", 3.0 if a.tiny else a.cpu_budget, a.threads, 32,
                               5 if a.tiny else a.steps, overrides, name,
                               ["--data", "synth:object:2", "--val-scenes", "synth:object:1"] if a.tiny else None)
        model, meta = load_checkpoint(run / "checkpoints" / "final")
        torch.set_num_threads(a.threads)
        r = evaluate(model, ["synth:eval"], (K,), None, synth_count=1 if a.tiny else 10, protocol_set="cpu",
                     max_targets=1 if a.tiny else None, cache=train_tiny.ROOT / "outputs" / "cache", progress=not a.tiny)
        metrics = r["means"]["synth"][str(K)]
        if meta["model_config"].get("output") == "colors":  # rows report the feature head as rgb, colours as aux
            metrics = {(k[:-4] if k.endswith("_aux") else f"{k}_aux" if f"{k}_aux" in metrics else k): v
                       for k, v in metrics.items()}
        result["rows"][row] = {"overrides": ROWS[row], "steps": meta["step"], "cpu_seconds": meta["extra"].get("cpu_s"),
                               "metrics": metrics}
        print(row, json.dumps(result["rows"][row]["metrics"]))
    write_json(a.out, result)
    return result

