"""Lever measurement: the same tiny model trained from scratch and with each pretrained encoder at the
same CPU budget (same seed, data, schedule, 1 thread), then scored on held-out real scenes and on
validation seeds. Not a shipped checkpoint: the runs stay in outputs/train/lever_<model>_<encoder>.

    python -m bench encoder_lever --model ibrnet-tiny --encoders scratch vgg16 alexnet --cpu-budget 300
    python -m bench encoder_lever --model ibrnet-tiny --encoders scratch vgg16 alexnet --eval-only

The schedule is constant after a 50-step warm-up, so that a run cut by its CPU budget is not at a
different point of a decaying schedule than its rival (the encoders differ in cost per step). Each
``--encoders`` entry trains in its own process, side by side. Results: bench/results/encoder_lever.json
(with a provenance header) and a Markdown table on stdout.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from bench.train_tiny import CACHE, REAL, RESOLUTION, SEED, SHARED, WEIGHTS

ROOT = Path(__file__).resolve().parents[1]

SYNTH = ["synth:object", "synth:frontal", "synth:forward"]
HELD_OUT = ["llff/fern", "neus_dtu/dtu_scan37"]
VAL_SEEDS = {"object": range(901000, 901001), "forward": range(901004, 901005)}
"""Validation scenes scored after training (1 object-rig, 1 forward-rig of the model cards' 901000-901007; few,
for the CPU time of a shared machine); never the held-out ones."""


def run_dir(model: str, encoder: str) -> Path:
    return ROOT / "outputs" / "train" / f"lever_{model}_{encoder}"


def data_args(synth_scenes: int) -> list[str]:
    real = [str(SHARED / r) for r in REAL if (SHARED / r).is_dir()]
    synth = [f"{s}:{synth_scenes}" for s in SYNTH]
    return ["--data", *synth, *real, "--data-weights", *map(str, WEIGHTS[:len(synth) + len(real)])]


def val_scene_dirs() -> list[Path]:
    from omnirecon.data.synth.generate import SynthOptions, generate_scene

    out = []
    for rig, seeds in VAL_SEEDS.items():
        for seed in seeds:
            out.append(generate_scene(ROOT / "outputs" / "cache" / "lever_val" / rig, seed,
                                      SynthOptions(rig=rig, views=40, resolution=RESOLUTION)))
    return out


def train(model: str, encoder: str, cpu_budget: float, synth_scenes: int) -> Path:
    out = run_dir(model, encoder)
    cmd = [sys.executable, "-m", "omnirecon.cli", "train", "--model", model, *data_args(synth_scenes),
           "--model-overrides", f"encoder={encoder}", "--resolution", str(RESOLUTION), "--steps", "100000",
           "--schedule", "constant", "--warmup", "50", "--cpu-budget", str(cpu_budget), "--threads", "1",
           "--seed", str(SEED), "--cache", str(CACHE), "--val-every", "0", "--ckpt-every", "0", "--out", str(out),
           "--no-progress"]
    if (out / "checkpoints" / "latest").exists():
        cmd.append("--resume")
    print(" ".join(cmd), flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.with_suffix(".log"), "w") as log:
        subprocess.run(cmd, check=True, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    return out


def evaluate(model: str, encoder: str, scenes: list[str], name: str) -> dict:
    out = run_dir(model, encoder) / f"eval_{name}"
    cmd = [sys.executable, "-m", "omnirecon.cli", "eval", "--ckpt", str(run_dir(model, encoder) / "checkpoints" / "final"),
           "--scenes", *scenes, "--protocol-set", "cpu", "--threads", "1", "--out", str(out), "--no-save-images"]
    print(" ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return json.loads((out / "results.json").read_text())


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="ibrnet-tiny")
    p.add_argument("--encoders", nargs="+", default=["scratch", "vgg16"])
    p.add_argument("--cpu-budget", type=float, default=300.0)
    p.add_argument("--synth-scenes", type=int, default=8, help="procedural training scenes per rig")
    p.add_argument("--eval-only", action="store_true", help="score finished runs only")
    a = p.parse_args(argv)
    if not a.eval_only:
        from bench import train_tiny
        from bench.train_tiny import prepare
        train_tiny.SYNTH = [f"{s}:{a.synth_scenes}" for s in SYNTH]
        prepare(a.synth_scenes)
        with ThreadPoolExecutor(len(a.encoders)) as pool:
            list(pool.map(lambda e: train(a.model, e, a.cpu_budget, a.synth_scenes), a.encoders))
    groups = {Path(s).name: [str(SHARED / s)] for s in HELD_OUT}
    groups["val"] = [str(d) for d in val_scene_dirs()]
    jobs = [(enc, scenes, name) for enc in a.encoders for name, scenes in groups.items()]  # one process each
    with ThreadPoolExecutor(len(jobs)) as pool:
        results = list(pool.map(lambda j: evaluate(a.model, *j), jobs))
    rows = {}
    for (enc, _, name), res in zip(jobs, results):
        meta = json.loads((run_dir(a.model, enc) / "checkpoints" / "final" / "meta.json").read_text())
        rows.setdefault(enc, {"step": meta["step"], "cpu_s": meta["extra"]["cpu_s"]})[name] = res
    from omnirecon.provenance import provenance

    result = {"provenance": provenance(SEED), "model": a.model, "cpu_budget": a.cpu_budget, "runs": rows}
    dest = ROOT / "bench" / "results" / "encoder_lever.json"
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps(result, indent=1, default=str))
    print(f"wrote {dest}")
    print(table(result))


def table(result: dict) -> str:
    """Markdown: PSNR per held-out scene (whole image; DTU also over the mask) and the validation mean, K = 3 / 10."""
    lines = ["| encoder | steps | CPU-s | fern | dtu_scan37 | dtu_scan37 (mask) | validation |", "|---|---|---|---|---|---|---|"]
    for enc, row in result["runs"].items():
        def pair(scenes, key="psnr", pick=None):
            vals = []
            for k in ("3", "10"):
                got = [s["settings"][k]["mean"][key] for s in scenes if pick is None or s["name"] == pick]
                vals.append(f"{sum(got) / len(got):.2f}" if got else "-")
            return " / ".join(vals)

        held = [s for name in row if name not in ("val", "step", "cpu_s") for s in row[name]["scenes"]]
        val = row["val"]["scenes"]
        lines.append(f"| {enc} | {row['step']} | {row['cpu_s']:.0f} | {pair(held, pick='fern')} | "
                     f"{pair(held, pick='dtu_scan37')} | {pair(held, 'psnr_masked', 'dtu_scan37')} | {pair(val)} |")
    return "\n".join(lines)

