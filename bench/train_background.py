"""Real training objects on black or random backgrounds: gpnr-tiny warm-started from the shipped checkpoint, one arm
per ``--real-background``, scored on validation data only (issue 47).

    python -m bench train_background                    # train every arm (100 CPU-s each, one at a time), score them
    python -m bench train_background --cpu-budget 300   # a longer probe: continues each arm's shorter run (exact resume)
    python -m bench train_background --eval-only        # score finished runs not yet scored, rewrite the JSON

Every arm continues checkpoints/gpnr-tiny (``--init``: fresh optimizer, constant learning rate 1e-4 after 20 warm-up
steps) for the same process-CPU budget (1 thread, seed 0) on the shipped checkpoint's data mix (procedural rigs at
weight 2, 8 scenes each, the real training scenes at weight 1), K drawn from [3, 10], differing only in
``--real-background``: ``white`` (the control: the RGBA objects lego and chair as read), ``black`` or ``random``. A new
scene is drawn at every step (``--switch-every 1``, every scene kept in memory once read), so that in the few dozen
steps of a probe the RGBA scenes get their share of steps (with ``--switch-every 10`` and seed 0 the first lego block
comes at step 161); every arm draws the same scenes, targets, sources and pixels (the background colour is drawn
after them). The arms render as the shipped checkpoint does (``render_samples=24``, ``render_bf16=true``: render-only
options).

Scored like ``python -m bench train_gpnr_gap``: the `cpu` protocol's targets and sources (64 px, K = 3), mean PSNR
over the target views (whole image, dB), on the held-out views of the real training scenes, on lego and chair again
with a black background behind the object, and on the procedural validation seeds of ``train_levers``. fern,
dtu_scan24/37 and the evaluation seeds are not looked at. Runs live in outputs/train/background_<arm>_<budget>cpu (a
longer budget starts from a copy of the arm's longest shorter run: the constant schedule makes that the same run);
results go to bench/results/train_background.json, one probe per budget (the table: `python -m bench page --reuse`).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench.train_levers import SYNTH, SYNTH_SCENES, VAL_SCENES
from bench.train_tiny import CACHE, REAL, SEED, SHARED

ROOT = Path(__file__).resolve().parents[1]
PARENT = ROOT / "checkpoints" / "gpnr-tiny"
ARMS = {"white": "control: lego and chair on white, as read", "black": "lego and chair on black",
        "random": "lego and chair per step on white, black or a random flat colour (equal odds)"}
CONTROL = "white"
SETTINGS = {"lr": 1e-4, "warmup": 20, "schedule": "constant", "switch_every": 1, "scenes_in_memory": 32,
            "num_views_range": [3, 10], "synth_scenes": SYNTH_SCENES, "num_views": 3}
BLACK = ["blender/lego", "blender/chair"]
"""Validation scenes also scored with a black background behind the object (as ``train_gpnr_gap``)."""
RGBA = ("lego", "chair")
"""The real training scenes read from RGBA images (the ones ``--real-background`` changes)."""
BETTER = 0.1
"""dB an arm must gain over the control on both the mean of the real validation rows and the mean of the black-
background rows to be called better (the bar of the warm-start section)."""


def run_dir(arm: str, budget: float, prefix: str = "background") -> Path:
    """The run of arm ``arm`` at ``budget`` CPU-s (``prefix``: ``continue<step>`` for a run from the checkpoint
    shipped at that step, ``--continue-shipped``)."""
    return ROOT / "outputs" / "train" / f"{prefix}_{arm}_{budget:g}cpu"


def train_cmd(arm: str, budget: float, prefix: str = "background") -> list[str]:
    real = [str(SHARED / r) for r in REAL if (SHARED / r).is_dir()]
    synth = [f"synth:{r}:{SYNTH_SCENES}" for r in SYNTH]
    s = SETTINGS
    cmd = [sys.executable, "-m", "omnirecon.cli", "train", "--model", "gpnr-tiny", "--init", str(PARENT),
           "--model-overrides", "render_samples=24", "render_bf16=true",
           "--data", *synth, *real, "--data-weights", *(["2.0"] * len(synth) + ["1.0"] * len(real)),
           "--real-background", arm, "--lr", str(s["lr"]), "--warmup", str(s["warmup"]), "--schedule", s["schedule"],
           "--steps", "100000", "--num-views-range", *map(str, s["num_views_range"]),
           "--switch-every", str(s["switch_every"]), "--scenes-in-memory", str(s["scenes_in_memory"]),
           "--cpu-budget", str(budget), "--threads", "1", "--seed", str(SEED), "--synth-scenes", str(SYNTH_SCENES),
           "--cache", str(CACHE), "--resolution", "64", "--val-every", "0", "--ckpt-every", "0", "--log-every", "1",
           "--out", str(run_dir(arm, budget, prefix)), "--no-progress"]
    if (run_dir(arm, budget, prefix) / "checkpoints" / "latest").exists():
        cmd.append("--resume")
    return cmd


def command(arm: str, budget: float, prefix: str = "background") -> str:
    """Arm ``arm``'s training command as a user types it from the checkout (no ``--resume``)."""
    cmd = ["python", *train_cmd(arm, budget, prefix)[1:]]
    text = " ".join(c for c in cmd if c != "--resume")
    return text.replace(str(SHARED), "../shared/data").replace(str(ROOT) + "/", "")


def train(arm: str, budget: float, prefix: str = "background") -> None:
    """Train arm ``arm`` to ``budget`` process CPU-s (resuming a cut run, or a copy of the arm's longest shorter
    run); procedural scenes are generated first."""
    from bench.train_levers import prepare

    out = run_dir(arm, budget, prefix)
    final = out / "checkpoints" / "final"
    if final.is_dir() and json.loads((final / "meta.json").read_text())["extra"]["cpu_s"] >= budget - 1:
        return
    shorter = sorted((float(d.name.rsplit("_", 1)[1][:-3]), d) for d in out.parent.glob(f"{prefix}_{arm}_*cpu")
                     if (d / "checkpoints" / "final").is_dir())
    shorter = [d for b, d in shorter if b < budget]
    if shorter and not out.exists():
        shutil.copytree(shorter[-1], out, symlinks=True)
        shutil.copy(shorter[-1].with_suffix(".log"), out.with_suffix(".log"))
    prepare(64, False)  # before the clock starts
    cmd = train_cmd(arm, budget, prefix)
    print(" ".join(cmd), flush=True)
    log = out.with_suffix(".log")
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as f:
        subprocess.run(cmd, check=True, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT)


def validation_scenes() -> list:
    """``(name, role, EvalScene)`` of every validation row: the real training scenes' held-out views, lego and chair
    on black, the procedural validation seeds."""
    from bench.train_gpnr_gap import eval_scene
    from omnirecon.data.synth.generate import SynthOptions, generate_scene
    from omnirecon.engine.scenes import prepare_scenes

    out = [(es.name, "real", es) for es in (eval_scene(r, None) for r in REAL if (SHARED / r).is_dir())]
    out += [(es.name, "black", es) for es in (eval_scene(r, "black") for r in BLACK if (SHARED / r).is_dir())]
    for rig, seeds in VAL_SCENES.items():
        for seed in seeds:
            path = generate_scene(ROOT / "outputs" / "cache" / "lever_val" / rig, seed,
                                  SynthOptions(rig=rig, views=40, resolution=64))
            es = prepare_scenes([str(path)], protocol_set="cpu")[0]
            out.append((f"synth:{rig}:{seed}", "procedural", es))
    return out


def score(ckpt: Path, scenes: list) -> dict:
    """Mean PSNR (dB) over the protocol's target views of each validation scene, K = 3."""
    from bench.train_gpnr_gap import score_scene
    from omnirecon.engine.machine import load_model

    model = load_model(ckpt, None)[0]
    cpu = time.process_time()
    psnr = {}
    for name, _, es in scenes:
        views = score_scene({"gpnr-tiny": model}, es, SETTINGS["num_views"], None)
        psnr[name] = round(sum(v["gpnr-tiny"]["psnr"] for v in views) / len(views), 3)
    return {"psnr": psnr, "eval_cpu_s": round(time.process_time() - cpu, 1)}


def figure(ckpts: dict[str, Path], es, dest: Path) -> None:
    """Per target of ``es`` (the protocol's, K = 3): ground truth | each checkpoint's render, 4x nearest upscaling."""
    import numpy as np
    from PIL import Image

    from bench.train_gpnr_gap import score_scene
    from omnirecon.engine.machine import load_model

    renders = []
    for ckpt in ckpts.values():
        pictures: list = []
        score_scene({"gpnr-tiny": load_model(ckpt, None)[0]}, es, SETTINGS["num_views"], pictures)
        renders.append(pictures)
    rows = [np.concatenate([es.scene.images[t].numpy(), *[r[i][3][0].numpy() for r in renders]], 1)
            for i, (_, _, t, _) in enumerate(renders[0])]  # [H, W * (1 + len(ckpts)), 3] each
    img = (np.concatenate(rows, 0).clip(0, 1) * 255).round().astype(np.uint8)
    dest.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img).resize((img.shape[1] * 4, img.shape[0] * 4), Image.NEAREST).save(dest)


def means(psnr: dict, roles: dict) -> dict:
    """Mean PSNR per group: ``real`` (held-out views, as read), ``black`` (lego and chair on black), ``validation``
    (both: every real validation row) and ``procedural``."""
    groups = {"real": ["real"], "black": ["black"], "validation": ["real", "black"], "procedural": ["procedural"]}
    out = {}
    for group, keep in groups.items():
        vals = [v for n, v in psnr.items() if roles[n] in keep]
        out[group] = round(sum(vals) / len(vals), 3) if vals else None
    return out


def rgba_steps(run: Path) -> int:
    """Steps the run spent on the RGBA scenes (metrics.jsonl logs every step's scene)."""
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines() if x.strip()]
    return sum(1 for r in rows if "scene" in r and r["scene"] in RGBA)


def means_minus_control(arms: dict, control: str) -> dict | None:
    """Each arm's group means minus the control's (``{arm: {group: dB}}``, the control left out); None without it."""
    if control not in arms:
        return None
    base = arms[control]["means"]
    return {a: {g: r["means"][g] - base[g] for g in r["means"]} for a, r in arms.items() if a != control}


def verdict(probe: dict) -> str:
    """Which arms of one probe beat the control on validation (by :data:`BETTER` on both the mean over every real
    validation row and the mean over the black-background rows), with their change on the rows as read."""
    d = means_minus_control(probe["arms"], CONTROL)
    if d is None:
        return "no control run yet"
    better = [a for a in d if d[a]["validation"] > BETTER and d[a]["black"] > BETTER]
    said = "; ".join(f"{a}: {d[a]['validation']:+.2f} on every real validation row, {d[a]['black']:+.2f} on black, "
                     f"{d[a]['real']:+.2f} as read, {d[a]['procedural']:+.2f} procedural" for a in d)
    if not better:
        return f"no arm beats the control by more than {BETTER:g} dB on both every real validation row and on black ({said})"
    best = max(better, key=lambda a: d[a]["validation"])
    return (f"{', '.join(better)} beat{'s' if len(better) == 1 else ''} the control by more than {BETTER:g} dB on "
            f"both every real validation row and on black, best {best} ({said})")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--arms", nargs="+", default=list(ARMS), choices=list(ARMS))
    p.add_argument("--cpu-budget", type=float, default=100.0, help="process CPU-s of training per arm")
    p.add_argument("--eval-only", action="store_true", help="score finished runs only")
    p.add_argument("--rescore", action="store_true",
                   help="score checkpoints again (else a checkpoint already scored, same step and CPU-s, keeps its scores)")
    p.add_argument("--shipped", action="store_true", help="score the parent checkpoint again (else once)")
    p.add_argument("--threads", type=int, default=1, help="torch threads of the scoring")
    p.add_argument("--continue-shipped", action="store_true",
                   help="train the control arm --cpu-budget more CPU-s from the checkpoint shipped now (its run: "
                        "outputs/train/continue<step>_white_<budget>cpu), score it beside that checkpoint and record "
                        "both under 'continued' (a candidate for the next ship: bench train_tiny --reship)")
    a = p.parse_args(argv)
    import torch

    from omnirecon.provenance import provenance

    torch.set_num_threads(a.threads)
    dest = ROOT / "bench" / "results" / "train_background.json"
    result = json.loads(dest.read_text()) if dest.is_file() else {}
    scenes = validation_scenes()
    roles = {name: role for name, role, _ in scenes}
    if a.continue_shipped:
        result.setdefault("continued", {})[f"{a.cpu_budget:g}"] = continued(a.cpu_budget, a.eval_only, scenes, roles)
        write(dest, result)
        return
    if a.shipped or "shipped" not in result:
        meta = json.loads((PARENT / "meta.json").read_text())
        s = score(PARENT, scenes)
        result["shipped"] = {"step": meta["step"], **s, "means": means(s["psnr"], roles)}
    probe = result.setdefault("probes", {}).setdefault(f"{a.cpu_budget:g}", {"arms": {}})
    for arm in a.arms:
        if not a.eval_only:
            train(arm, a.cpu_budget)
        final = run_dir(arm, a.cpu_budget) / "checkpoints" / "final"
        if not final.is_dir():
            continue
        meta = json.loads((final / "meta.json").read_text())
        old = probe["arms"].get(arm, {})
        same = (old.get("steps"), old.get("cpu_s")) == (meta["step"], round(meta["extra"]["cpu_s"], 1))
        s = {k: old[k] for k in ("psnr", "eval_cpu_s")} if same and not a.rescore and set(old["psnr"]) == set(roles) \
            else score(final, scenes)
        probe["arms"][arm] = {"what": ARMS[arm], "steps": meta["step"], "cpu_s": round(meta["extra"]["cpu_s"], 1),
                              "rgba_steps": rgba_steps(run_dir(arm, a.cpu_budget)), **s,
                              "means": means(s["psnr"], roles),
                              "command": command(arm, a.cpu_budget)}
        print(f"{arm}: {json.dumps(probe['arms'][arm]['means'])}", flush=True)
    control = probe["arms"].get(CONTROL)
    for arm, r in probe["arms"].items():
        if control is not None:
            r["minus_control"] = {k: round(v - control["psnr"][k], 3) for k, v in r["psnr"].items()}
            r["means_minus_control"] = {k: round(v - control["means"][k], 3) for k, v in r["means"].items()}
    probe.update(cpu_budget=a.cpu_budget, verdict=verdict(probe), provenance=provenance(SEED))
    if set(probe["arms"]) == set(ARMS):  # chair on black: ground truth | shipped | each arm
        dest_png = ROOT / "bench" / "results" / "figures" / f"train_background_chair_black_{a.cpu_budget:g}cpu.png"
        es = next(es for name, _, es in scenes if name == "chair (black background)")
        figure({"shipped": PARENT, **{arm: run_dir(arm, a.cpu_budget) / "checkpoints" / "final" for arm in ARMS}}, es,
               dest_png)
        probe["figure"] = str(dest_png.relative_to(ROOT))
        probe["figure_columns"] = ["ground truth", "shipped gpnr-tiny", *ARMS]
    template = command("ARM", 1).replace("background_ARM_1cpu", "background_<arm>_<budget>cpu").replace(
        "--cpu-budget 1 ", "--cpu-budget <budget> ").replace("--real-background ARM", "--real-background <arm>")
    result.update(roles=roles, settings=SETTINGS, parent=str(PARENT.relative_to(ROOT)), command=template,
                  provenance=provenance(SEED))
    write(dest, result)
    print(probe["verdict"])
    print(f"wrote {dest} (the table: python -m bench page --reuse)")


def write(dest: Path, result: dict) -> None:
    """``result`` to ``dest``, atomically."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(dest)


def continued(budget: float, eval_only: bool, scenes: list, roles: dict) -> dict:
    """``--continue-shipped``: the control arm's settings for ``budget`` more CPU-s from the checkpoint shipped now,
    scored beside it on the same validation rows; ``better``: by more than :data:`BETTER` dB on both the mean over
    every real validation row and on the procedural seeds."""
    from omnirecon.provenance import provenance

    meta = json.loads((PARENT / "meta.json").read_text())
    prefix = f"continue{meta['step']}"
    if not eval_only:
        train(CONTROL, budget, prefix)
    final = run_dir(CONTROL, budget, prefix) / "checkpoints" / "final"
    run_meta = json.loads((final / "meta.json").read_text())
    before, after = score(PARENT, scenes), score(final, scenes)
    before["means"], after["means"] = means(before["psnr"], roles), means(after["psnr"], roles)
    change = {g: round(after["means"][g] - before["means"][g], 3) for g in after["means"]}
    out = {"parent_step": meta["step"], "parent_cpu_s": round(meta.get("extra", {}).get("cpu_s", 0.0), 1),
           "steps": run_meta["step"], "cpu_s": round(run_meta["extra"]["cpu_s"], 1), "shipped": before,
           "continued": after, "change": change,
           "better": change["validation"] > BETTER and change["procedural"] > BETTER, "bar_db": BETTER,
           "command": command(CONTROL, budget, prefix), "provenance": provenance(SEED)}
    print(json.dumps({k: out[k] for k in ("parent_step", "steps", "cpu_s", "change", "better")}), flush=True)
    return out
