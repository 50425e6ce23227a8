"""Novel-view quality of the shipped tiny checkpoints and the non-learned floor.

    python -m bench quality                         # floor and the shipped tiny checkpoints, every evaluation scene
    python -m bench quality --models floor --tiny   # a fast subset (tests)

Held-out procedural scenes (``synth:eval``, seeds 900000+) and the real scenes dtu_scan24,
dtu_scan37, fern (never trained on), fox and lego (training scenes: fitting, not generalisation),
with 3 and 10 source views, under the ``cpu`` protocol set of ``omnirecon.engine.evaluate`` (64 px long side,
fewer targets; docs/evaluation.md). Writes ``bench/results/quality_<model>.json``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from omnirecon.data.io import write_json

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
REAL = ["neus_dtu/dtu_scan24", "neus_dtu/dtu_scan37", "llff/fern", "instant_ngp/fox", "blender/lego"]


def scenes(tiny: bool) -> list[str]:
    if tiny:
        return ["synth:eval"]
    return ["synth:eval", *[str(SHARED / r) for r in REAL if (SHARED / r).is_dir()]]


def run(model_name: str, out_dir: Path, tiny: bool, threads: int) -> dict:
    from omnirecon.engine.checkpoint import fingerprint, load_checkpoint
    from omnirecon.engine.evaluate import evaluate
    from omnirecon.models.registry import build_model

    torch.set_num_threads(threads)
    if model_name == "floor":
        model, info = build_model("floor"), {"name": "floor", "preset": "floor"}
    else:
        ckpt = ROOT / "checkpoints" / model_name
        model, meta = load_checkpoint(ckpt)
        info = {"name": model_name, "preset": meta["preset"], "checkpoint": str(ckpt.relative_to(ROOT)),
                "step": meta["step"], "cpu_seconds": meta["extra"].get("cpu_s"), "sha256": fingerprint(ckpt)["sha256"]}
    result = evaluate(model, scenes(tiny), (3,) if tiny else (3, 10), ROOT / "outputs" / "bench" / f"eval_{model_name}",
                      model_info=info, synth_count=1 if tiny else 10, protocol_set="cpu",
                      max_targets=1 if tiny else None, cache=ROOT / "outputs" / "cache", progress=not tiny)
    write_json(out_dir / f"quality_{model_name}.json", result)
    return result


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", nargs="+", default=["floor", "gpnr-tiny", "ibrnet-tiny", "omnirecon-tiny"])
    p.add_argument("--tiny", action="store_true", help="one procedural scene, one target, K=3 (tests)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    for m in a.models:
        r = run(m, a.out, a.tiny, a.threads)
        print(m, {proto: {k: round(v.get("psnr", float("nan")), 2) for k, v in ks.items()} for proto, ks in r["means"].items()})

