"""The levers of gpnr-tiny's DTU deficit not yet tried (issue 47): DTU's 4:3 aspect and a wider source pool, each a
warm start of the shipped gpnr-tiny against a control, scored on validation data only.

    python -m bench train_gpnr_levers                       # train every arm (300 CPU-s each), score them
    python -m bench train_gpnr_levers --arms pool --train-only   # one arm's training (arms may run side by side)
    python -m bench train_gpnr_levers --eval-only           # score finished runs, rewrite the JSON

Every arm continues checkpoints/gpnr-tiny (``--init``: fresh optimizer, constant learning rate 1e-4 after 20 warm-up
steps) for the same process-CPU budget (1 thread, seed 0) on the data mix of ``python -m bench train_background``'s
control (procedural rigs at weight 2, 8 scenes each, the real training scenes at weight 1, lego and chair on white),
K drawn from [3, 10], a new scene at every step. The procedural scenes are the same seeds in every arm, generated into
folders of their own (``outputs/cache/synth_aspect``) and passed as data:

* ``control``: square procedural scenes (as shipped), sources drawn from the target's 2K nearest views (as shipped);
* ``aspect``: the same procedural scenes at DTU's 4:3 (``omnirecon synth --aspect 0.75``: the square images' middle
  rows, the same horizontal field of view);
* ``pool``: square scenes, the K sources drawn from the target's 20 nearest views (``--pool 20``: wider baselines, as
  DTU's protocol sources lie far from its targets).

Scored like ``python -m bench train_background`` (the `cpu` protocol's targets and sources, 64 px, K = 3, mean PSNR
over the target views, whole image, dB): the held-out views of the real training scenes, lego and chair on black, the
procedural validation seeds of ``train_levers``, and the same seeds at 4:3. fern, dtu_scan24/37 and the evaluation
seeds are not looked at. Runs: outputs/train/gpnrlever_<arm>_<budget>cpu; results: bench/results/train_gpnr_levers.json
(the table: ``python -m bench page --reuse``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from bench.train_background import PARENT, SETTINGS, means, means_minus_control, score, validation_scenes, write
from bench.train_levers import SYNTH, VAL_SCENES, synth_refs
from bench.train_tiny import CACHE, REAL, SEED, SHARED

ROOT = Path(__file__).resolve().parents[1]
ARMS = {"control": "square procedural scenes, sources from the 2K nearest views (as shipped)",
        "aspect": "procedural scenes at 4:3 (DTU's aspect)",
        "pool": "sources from the 20 nearest views (--pool 20)"}
CONTROL = "control"
ASPECT = 0.75
"""DTU's image aspect (1200 / 1600)."""
POOL = 20
"""The wider pool's views (the shipped runs draw from the target's 2K nearest: 6 to 20 for K in [3, 10])."""
BUDGET = 300.0
BETTER = 0.1
"""dB an arm must gain over the control on both the mean of every real validation row and the mean of the procedural
seeds (square and 4:3) to be called better."""


def run_dir(arm: str, budget: float) -> Path:
    return ROOT / "outputs" / "train" / f"gpnrlever_{arm}_{budget:g}cpu"


def synth_folders(aspect: float) -> list[Path]:
    """One folder per rig holding the procedural training scenes (the shipped runs' seeds) at ``aspect``, generated
    before the clock starts."""
    from omnirecon.data.synth.generate import SynthOptions, generate_scene

    folders = []
    for rig, refs in zip(SYNTH, synth_refs(64)):
        folder = CACHE.parent / "synth_aspect" / f"{rig}_64_aspect{aspect:g}"
        for r in refs:
            if not (folder / r.path.name).is_dir():
                generate_scene(folder, r.seed, SynthOptions(rig=rig, views=40, resolution=64, aspect=aspect))
        folders.append(folder)
    return folders


def train_cmd(arm: str, budget: float) -> list[str]:
    real = [str(SHARED / r) for r in REAL if (SHARED / r).is_dir()]
    synth = [str(f) for f in synth_folders(ASPECT if arm == "aspect" else 1.0)]
    s = SETTINGS
    cmd = [sys.executable, "-m", "omnirecon.cli", "train", "--model", "gpnr-tiny", "--init", str(PARENT),
           "--model-overrides", "render_samples=24", "render_bf16=true",
           "--data", *synth, *real, "--data-weights", *(["2.0"] * len(synth) + ["1.0"] * len(real)),
           "--lr", str(s["lr"]), "--warmup", str(s["warmup"]), "--schedule", s["schedule"],
           "--steps", "100000", "--num-views-range", *map(str, s["num_views_range"]),
           "--switch-every", str(s["switch_every"]), "--scenes-in-memory", str(s["scenes_in_memory"]),
           "--cpu-budget", str(budget), "--threads", "1", "--seed", str(SEED),
           "--resolution", "64", "--val-every", "0", "--ckpt-every", "0", "--log-every", "1",
           "--out", str(run_dir(arm, budget)), "--no-progress"]
    if arm == "pool":
        cmd += ["--pool", str(POOL)]
    if (run_dir(arm, budget) / "checkpoints" / "latest").exists():
        cmd.append("--resume")
    return cmd


def command(arm: str, budget: float) -> str:
    """Arm ``arm``'s training command as a user types it from the checkout (no ``--resume``)."""
    text = " ".join(c for c in ["python", *train_cmd(arm, budget)[1:]] if c != "--resume")
    return text.replace(str(SHARED), "../shared/data").replace(str(ROOT) + "/", "")


def train(arm: str, budget: float) -> None:
    """Train arm ``arm`` to ``budget`` process CPU-s (resuming a cut run)."""
    final = run_dir(arm, budget) / "checkpoints" / "final"
    if final.is_dir() and json.loads((final / "meta.json").read_text())["extra"]["cpu_s"] >= budget - 1:
        return
    cmd = train_cmd(arm, budget)  # generates the procedural scenes first
    print(" ".join(cmd), flush=True)
    log = run_dir(arm, budget).with_suffix(".log")
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as f:
        subprocess.run(cmd, check=True, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT)


def wide_scenes() -> list:
    """``(name, role, EvalScene)`` of the procedural validation seeds at 4:3."""
    from omnirecon.data.synth.generate import SynthOptions, generate_scene
    from omnirecon.engine.scenes import prepare_scenes

    out = []
    for rig, seeds in VAL_SCENES.items():
        for seed in seeds:
            path = generate_scene(ROOT / "outputs" / "cache" / "lever_val_aspect" / rig, seed,
                                  SynthOptions(rig=rig, views=40, resolution=64, aspect=ASPECT))
            out.append((f"synth:{rig}:{seed} (4:3)", "procedural 4:3", prepare_scenes([str(path)], protocol_set="cpu")[0]))
    return out


def group_means(psnr: dict, roles: dict) -> dict:
    """:func:`bench.train_background.means` plus ``procedural 4:3`` and ``all procedural`` (square and 4:3)."""
    out = means({k: v for k, v in psnr.items() if roles[k] != "procedural 4:3"}, roles)
    for group, keep in {"procedural 4:3": ["procedural 4:3"], "all procedural": ["procedural", "procedural 4:3"]}.items():
        vals = [v for n, v in psnr.items() if roles[n] in keep]
        out[group] = round(sum(vals) / len(vals), 3) if vals else None
    return out


def verdict(arms: dict) -> str:
    d = means_minus_control(arms, CONTROL)
    if d is None:
        return "no control run yet"
    better = [a for a in d if d[a]["validation"] > BETTER and d[a]["all procedural"] > BETTER]
    said = "; ".join(f"{a}: {d[a]['validation']:+.2f} on every real validation row ({d[a]['black']:+.2f} on black), "
                     f"{d[a]['all procedural']:+.2f} procedural ({d[a]['procedural 4:3']:+.2f} at 4:3)" for a in d)
    if not better:
        return (f"no arm beats the control by more than {BETTER:g} dB on both every real validation row and the "
                f"procedural seeds ({said})")
    return f"{', '.join(better)} beat the control by more than {BETTER:g} dB on both ({said})"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--arms", nargs="+", default=list(ARMS), choices=list(ARMS))
    p.add_argument("--cpu-budget", type=float, default=BUDGET, help="process CPU-s of training per arm")
    p.add_argument("--train-only", action="store_true", help="train the arms, score nothing")
    p.add_argument("--eval-only", action="store_true", help="score finished runs only")
    p.add_argument("--threads", type=int, default=1, help="torch threads of the scoring")
    a = p.parse_args(argv)
    import torch

    from omnirecon.provenance import provenance

    if not a.eval_only:
        for arm in a.arms:
            train(arm, a.cpu_budget)
    if a.train_only:
        return
    torch.set_num_threads(a.threads)
    dest = ROOT / "bench" / "results" / "train_gpnr_levers.json"
    result = json.loads(dest.read_text()) if dest.is_file() else {}
    scenes = validation_scenes() + wide_scenes()
    roles = {name: role for name, role, _ in scenes}
    if "shipped" not in result or set(result["shipped"]["psnr"]) != set(roles):
        meta = json.loads((PARENT / "meta.json").read_text())
        s = score(PARENT, scenes)
        result["shipped"] = {"step": meta["step"], **s, "means": group_means(s["psnr"], roles)}
    probe = result.setdefault("probes", {}).setdefault(f"{a.cpu_budget:g}", {"arms": {}})
    for arm in a.arms:
        final = run_dir(arm, a.cpu_budget) / "checkpoints" / "final"
        if not final.is_dir():
            continue
        meta = json.loads((final / "meta.json").read_text())
        s = score(final, scenes)
        probe["arms"][arm] = {"what": ARMS[arm], "steps": meta["step"], "cpu_s": round(meta["extra"]["cpu_s"], 1),
                              **s, "means": group_means(s["psnr"], roles), "command": command(arm, a.cpu_budget)}
        print(f"{arm}: {json.dumps(probe['arms'][arm]['means'])}", flush=True)
    control = probe["arms"].get(CONTROL)
    for r in probe["arms"].values():
        if control is not None:
            r["minus_control"] = {k: round(v - control["psnr"][k], 3) for k, v in r["psnr"].items()}
            r["means_minus_control"] = {k: round(v - control["means"][k], 3) for k, v in r["means"].items()}
    probe.update(cpu_budget=a.cpu_budget, verdict=verdict(probe["arms"]), provenance=provenance(SEED))
    result.update(roles=roles, settings={**SETTINGS, "aspect": ASPECT, "pool": POOL},
                  parent=str(PARENT.relative_to(ROOT)), provenance=provenance(SEED))
    write(dest, result)
    print(probe["verdict"])
    print(f"wrote {dest} (the table: python -m bench page --reuse)")


if __name__ == "__main__":
    main()
