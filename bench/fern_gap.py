"""Omni-Recon's fern gap: the shipped omnirecon-tiny with its feature-volume box as before (the content box alone)
and as now on forward-facing rigs (grown to hold the source cameras), plus render-time options, scored on
validation (procedural forward-rig seeds 901004-901007: object rigs are unchanged by the box) and on fern.

    python -m bench fern_gap                                  # content vs cameras, validation and fern
    python -m bench fern_gap --variants content cameras cameras+far
    python -m bench fern_gap --variants cameras cameras+far --object-val --reuse   # add the object-rig seeds
    python -m bench fern_gap --variants cameras cameras+backdrop --object-val --real-val --dtu \
        --out bench/results/fern_gap_coarse.json     # the checkpoint's render pass as shipped (coarse since session 10)

No retraining: every variant is the same weights with one config field changed (``forward_box``, ``leftover``); the
render pass is the checkpoint's own (recorded as ``render_fine_pass``). Validation decides (procedural seeds and,
with ``--real-val``, the held-out views of the real training scenes, which training never draws); fern and, with
``--dtu``, dtu_scan24/37 (PSNR over the mask) are reported for the table only. Writes ``bench/results/fern_gap.json`` (provenance header,
CPU seconds of each evaluation, load average) and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import torch

from bench.train_tiny import REAL

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
VAL_SEEDS = {"forward": range(901004, 901008), "object": range(901000, 901004)}
"""The two halves of the model cards' validation seeds 901000-901007 (the box changes only the forward ones;
``leftover`` changes both)."""
VARIANTS = {
    "content": {"forward_box": "content", "leftover": "black"},
    "cameras": {"forward_box": "cameras", "leftover": "black"},
    "cameras+far": {"forward_box": "cameras", "leftover": "far"},
    "cameras+renormalize": {"forward_box": "cameras", "leftover": "renormalize"},
    "cameras+backdrop": {"forward_box": "cameras", "leftover": "backdrop"},
}
"""Config changes of each variant on top of the checkpoint's own config (each names both fields, so a variant means
the same whatever the shipped meta.json holds)."""


def val_scenes(rig: str, resolution: int = 64) -> list[Path]:
    from omnirecon.data.synth.generate import SynthOptions, generate_scene

    return [generate_scene(ROOT / "outputs" / "cache" / "val" / rig, seed,
                           SynthOptions(rig=rig, views=40, resolution=resolution)) for seed in VAL_SEEDS[rig]]


def score(model, scenes: list, protocol_set: str) -> dict:
    from omnirecon.engine.evaluate import evaluate

    cpu0 = time.process_time()
    res = evaluate(model, scenes, (3, 10), None, protocol_set=protocol_set, progress=False, save_images=False,
                   cache=ROOT / "outputs" / "cache")
    def psnr(s: dict, k: str) -> float:  # DTU over its mask (the goals' measure), every other scene whole image
        m = s["settings"][k]["mean"]
        return m.get("psnr_masked", m["psnr"])

    per_k = {k: sum(psnr(s, k) for s in res["scenes"]) / len(res["scenes"]) for k in ("3", "10")}
    return {"psnr": per_k, "per_scene": {s["name"]: {k: psnr(s, k) for k in ("3", "10")} for s in res["scenes"]},
            "cpu_s": time.process_time() - cpu0}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", type=Path, default=ROOT / "checkpoints" / "omnirecon-tiny")
    p.add_argument("--variants", nargs="+", default=["content", "cameras"], choices=list(VARIANTS))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "fern_gap.json")
    p.add_argument("--object-val", action="store_true", help="also score the object-rig validation seeds")
    p.add_argument("--reuse", action="store_true", help="keep the cells --out already holds; score the missing ones")
    p.add_argument("--real-val", action="store_true",
                   help="also score the held-out views of the real training scenes (validation)")
    p.add_argument("--dtu", action="store_true", help="also report dtu_scan24/37 (held out; PSNR over the mask)")
    a = p.parse_args(argv)
    from omnirecon.data.io import write_json
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.models.registry import build_model
    from omnirecon.provenance import provenance

    torch.set_num_threads(a.threads)
    groups = {"validation (forward seeds 901004-901007)": [str(s) for s in val_scenes("forward")],
              "fern": [str(SHARED / "llff" / "fern")]}
    if a.object_val:
        groups["validation (object seeds 901000-901003)"] = [str(s) for s in val_scenes("object")]
    if a.real_val:
        groups["validation (held-out views of " + ", ".join(Path(r).name for r in REAL) + ")"] = [
            str(SHARED / r) for r in REAL if (SHARED / r).is_dir()]
    if a.dtu:
        groups["dtu_scan24, dtu_scan37 (mask)"] = [str(SHARED / "neus_dtu" / s) for s in ("dtu_scan24", "dtu_scan37")]
    old = json.loads(a.out.read_text()) if a.reuse and a.out.is_file() else {"rows": {}, "variants": {}}
    rows: dict[str, dict] = old["rows"]
    model, meta = load_checkpoint(a.ckpt)
    base = model.cfg
    for name in ["floor", *a.variants]:
        if name != "floor":
            model.cfg = dataclasses.replace(base, **VARIANTS[name])
        row = rows.setdefault(name, {})
        for g, scenes in groups.items():
            if g not in row:
                row[g] = score(build_model("floor") if name == "floor" else model, scenes, "cpu")
        print(name, {g: {k: round(v, 2) for k, v in r["psnr"].items()} for g, r in row.items()}, flush=True)
    result = {"provenance": provenance(0, threads=a.threads, load_average=os.getloadavg()),
              "checkpoint": str(a.ckpt.relative_to(ROOT)) if a.ckpt.is_relative_to(ROOT) else str(a.ckpt),
              "step": meta["step"], "protocol_set": "cpu", "render_fine_pass": base.render_fine_pass,
              "variants": {**old["variants"], **{k: VARIANTS[k] for k in a.variants}},
              "rows": rows}
    write_json(a.out, result)
    print(f"wrote {a.out}")
    print(table(result))


def table(result: dict) -> str:
    """Markdown: mean PSNR K = 3 / 10 per scene group, and the margin over the floor."""
    groups = list(result["rows"]["floor"])
    na = {"psnr": {"3": float("nan"), "10": float("nan")}, "cpu_s": 0.0}
    lines = ["| variant | " + " | ".join(groups) + " | CPU-s |", "|---" * (len(groups) + 2) + "|"]
    for name, row in result["rows"].items():
        cells = []
        for g in groups:
            v, f = row.get(g, na)["psnr"], result["rows"]["floor"][g]["psnr"]
            margin = "" if name == "floor" else " ({:+.2f} / {:+.2f})".format(v["3"] - f["3"], v["10"] - f["10"])
            cells.append(f"{v['3']:.2f} / {v['10']:.2f}{margin}")
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {sum(r['cpu_s'] for r in row.values()):.0f} |")
    return "\n".join(lines)

