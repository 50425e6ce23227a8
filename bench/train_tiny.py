"""Train a tiny preset for a fixed CPU budget and ship its checkpoint with a model card.

    python -m bench train_tiny --model gpnr-tiny --cpu-budget 1800 --threads 1
    python -m bench train_tiny --model ibrnet-tiny --cpu-budget 1800 --threads 1

Every preset gets the same data, resolution, budget and seed. Procedural training scenes are
generated before the clock starts (``--prepare`` only generates them), so the budget is spent on
optimisation alone. The budget is process CPU seconds (``omnirecon train --cpu-budget``), which
other jobs sharing the machine do not shrink. The final checkpoint is copied to
``checkpoints/<model>/`` with ``MODEL_CARD.md`` and ``card.json`` (data, command, budget, steps,
training curve numbers, provenance).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
RESOLUTION = 64
SEED = 0
CACHE = ROOT / "outputs" / "cache" / "synth"
SYNTH = ["synth:object", "synth:frontal", "synth:forward"]
REAL = ["blender/lego", "blender/chair", "instant_ngp/fox", "llff/ethiopianHead"]  # never dtu_scan24/37 or fern
WEIGHTS = [2.0, 2.0, 2.0, 1.0, 1.0, 1.0, 1.0]


def weights(real_weight: float = 1.0) -> list[float]:
    """Mixing weights: procedural rigs as WEIGHTS, each real training scene ``real_weight``."""
    return WEIGHTS[:len(SYNTH)] + [real_weight] * len(REAL)


def data_args(real_weight: float = 1.0) -> list[str]:
    real = [str(SHARED / r) for r in REAL if (SHARED / r).is_dir()]
    weights_ = weights(real_weight)[:len(SYNTH) + len(real)]
    return ["--data", *SYNTH, *real, "--data-weights", *map(str, weights_)]


def _gen(task):
    from omnirecon.data.synth.generate import SynthOptions, generate_scene

    folder, seed, rig = task
    generate_scene(folder, seed, SynthOptions(rig=rig, views=40, resolution=RESOLUTION))


def prepare(synth_scenes: int) -> None:
    """Generate the procedural training and validation scenes the runs will use."""
    from omnirecon.data.bank import parse_sources

    tasks = []
    for role, specs in (("train", SYNTH), ("val", ["synth:object:2"])):
        for refs in parse_sources(specs, role, seed=SEED, synth_scenes=synth_scenes, cache=CACHE, resolution=RESOLUTION,
                                  synth_views=40):
            tasks += [(r.path.parent, r.seed, r.rig) for r in refs if not r.path.is_dir()]
    with ProcessPoolExecutor(2) as pool:
        list(pool.map(_gen, tasks))
    print(f"prepared {len(tasks)} procedural scenes in {CACHE}")


def train(model: str, cpu_budget: float, threads: int, synth_scenes: int, steps: int, overrides: list[str] = (),
          name: str | None = None, data: list[str] | None = None, stop_at: int | None = None,
          views: tuple[int, int] | None = None, tune: dict | None = None) -> Path:
    """Run ``omnirecon train`` (resuming an interrupted run) and return its run folder. ``tune``: a warm start
    (``init``: checkpoint folder, ``lr``, ``warmup``) and ``real_weight`` (the real scenes' mixing weight)."""
    tune = {k: v for k, v in (tune or {}).items() if v is not None}
    out = ROOT / "outputs" / "train" / (name or f"{model}_bench")
    cmd = [sys.executable, "-m", "omnirecon.cli", "train", "--model", model,
           *(data or data_args(tune.get("real_weight", 1.0))),
           *(["--init", str(tune["init"])] if "init" in tune else []),
           *(["--lr", str(tune["lr"])] if "lr" in tune else []),
           *(["--warmup", str(tune["warmup"])] if "warmup" in tune else []),
           *(["--model-overrides", *overrides] if overrides else []),
           "--synth-scenes", str(synth_scenes), "--resolution", str(RESOLUTION), "--steps", str(steps),
           "--cpu-budget", str(cpu_budget), "--threads", str(threads), "--seed", str(SEED), "--cache", str(CACHE),
           "--val-every", "500", "--ckpt-every", "250", "--out", str(out), "--no-progress",
           *(["--stop-at", str(stop_at)] if stop_at else []),
           *(["--num-views-range", str(views[0]), str(views[1])] if views else [])]
    start = 0
    if (out / "checkpoints" / "latest").exists():
        cmd.append("--resume")
        start = json.loads((out / "checkpoints" / "latest" / "meta.json").read_text())["step"]
    print(" ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT)
    # recorded once the run made (and marked) its folder: train writes only into a folder it owns
    record_stage(out, {"cpu_budget": cpu_budget, "steps": steps, "threads": threads, "from_step": start,
                       **ended_at(out, steps, stop_at),
                       **({"model_overrides": list(overrides)} if overrides else {}),
                       **({"num_views_range": list(views)} if views else {}),
                       **{k: str(v) for k, v in tune.items()}})
    return out


def ended_at(run: Path, steps: int, stop_at: int | None) -> dict:
    """``{"stop_at": step}`` for a stage given ``--stop-at`` or ended early (SIGTERM, the CPU budget): the step of
    the run's latest checkpoint, so that the stage's recorded command stops where the run did; ``{}`` for a stage
    that finished its ``steps``-long schedule."""
    latest = run / "checkpoints" / "latest" / "meta.json"
    reached = json.loads(latest.read_text())["step"] if latest.is_file() else None
    end = min(stop_at or steps, steps)
    if reached is not None and reached < end:
        return {"stop_at": reached}
    return {"stop_at": stop_at} if stop_at else {}


def record_stage(run: Path, stage: dict) -> None:
    """Append one invocation to ``run/stages.json`` (a run continued with a larger budget or a longer
    schedule has several; the model card lists them so the checkpoint can be regenerated)."""
    path = run / "stages.json"
    stages = json.loads(path.read_text()) if path.is_file() else []
    if stages and stages[-1] == stage:
        return  # an interrupted invocation resumed with the same flags
    run.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(stages + [stage], indent=1))
    tmp.replace(path)


def stage_commands(model: str, run: Path, cpu_budget: float, steps: int, threads: int) -> list[str]:
    """The ``train_tiny.py`` invocations that produced the run, in order (a stage that ran another command, e.g. an arm
    of ``python -m bench train_background``, records it verbatim as ``command``)."""
    path = run / "stages.json"
    stages = json.loads(path.read_text()) if path.is_file() else \
        [{"cpu_budget": cpu_budget, "steps": steps, "threads": threads, "from_step": 0}]
    return [st["command"] if "command" in st else f"python -m bench train_tiny --model {model} --cpu-budget {st['cpu_budget']:g} --steps {st['steps']} "
            f"--threads {st['threads']}" + (f" --stop-at {st['stop_at']}" if st.get("stop_at") else "")
            + (" --num-views-range {} {}".format(*st["num_views_range"]) if st.get("num_views_range") else "")
            + "".join(f" --{o.replace('=', ' ', 1)}" for o in st.get("model_overrides", []))
            + "".join(f" --{k.replace('_', '-')} {st[k]}" for k in ("init", "lr", "warmup", "real_weight") if k in st)
            for st in stages]


def parent_stages(parent: dict | None) -> list[tuple[str, dict]]:
    """(command, span) of each stage of a warm start's parent checkpoint, in the ``python -m bench`` form."""
    if not parent:
        return []
    spans = parent.get("stage_spans") or [None] * len(parent.get("stages") or [])
    return [(c.replace("python bench/train_tiny.py", "python -m bench train_tiny"), sp)
            for c, sp in zip(parent.get("stages") or [], spans)]


def parent_card(run: Path) -> dict | None:
    """The card of the checkpoint a warm-started run began from (``--init`` of its first stage), or None. Kept in the
    run as ``parent_card.json`` when first read: once the run ships into the same folder, the folder's card is the
    run's own, and reading it as the parent would count the parent's steps twice."""
    path = run / "stages.json"
    stages = json.loads(path.read_text()) if path.is_file() else []
    if not stages or "init" not in stages[0]:
        return None
    kept = run / "parent_card.json"
    if kept.is_file():
        return {"init": stages[0]["init"], **json.loads(kept.read_text())}
    card_file = ROOT / stages[0]["init"] / "card.json"
    card = json.loads(card_file.read_text()) if card_file.is_file() else {}
    kept.write_text(json.dumps(card, indent=1))
    return {"init": stages[0]["init"], **card}


def stage_spans(run: Path, rows: list[dict], last_step: int) -> list[dict]:
    """Steps and CPU seconds of each ``stages.json`` invocation, from the cumulative ``cpu_time`` that
    ``metrics.jsonl`` logs (the last row at or before each stage's first and last step)."""
    path = run / "stages.json"
    stages = json.loads(path.read_text()) if path.is_file() else [{"from_step": 0}]
    cpu = sorted((r["step"], r["cpu_time"]) for r in rows if "cpu_time" in r)

    def cpu_at(step: int) -> float:
        return max((c for s, c in cpu if s <= step), default=0.0)

    ends = [st["from_step"] for st in stages[1:]] + [last_step]
    return [{"from_step": st["from_step"], "to_step": end, "cpu_s": cpu_at(end) - cpu_at(st["from_step"])}
            for st, end in zip(stages, ends)]


def plot_curve(rows: list[dict], path: Path, title: str, restarts: list[int] = (),
               view_changes: list[tuple[int, list[int] | None]] = (), before: dict | None = None,
               warm_at: int | None = None) -> None:
    """Training PSNR (sampled rays, a running mean over 50 logs) and validation PSNR against step, as a PNG.
    ``before``: the curve (card.json ``curve``) of the checkpoint a warm-started run began from at ``warm_at``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    train = [(r["step"], r["psnr"]) for r in rows if "psnr" in r and "loss" in r]
    val = [(r["step"], r["val_psnr"]) for r in rows if "val_psnr" in r]
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    if before and before.get("train"):
        steps, psnr = np.array(before["train"]).T
        ax.plot(steps, psnr, color="0.6", lw=0.6, label="warm-start checkpoint's run (every 10th log)")
        if before.get("validation"):
            ax.plot(*np.array(before["validation"]).T, "o-", color="C3", ms=3, alpha=0.5)
    if warm_at is not None:
        ax.axvline(warm_at, color="C1", ls="--", lw=1.0, label="warm start: new data mix and schedule")
    if train:
        steps, psnr = np.array(train).T
        k = min(50, len(psnr))
        smooth = np.convolve(psnr, np.ones(k) / k, mode="valid")
        ax.plot(steps, psnr, color="0.8", lw=0.6, label="train (sampled rays)")
        ax.plot(steps[k - 1:], smooth, color="C0", lw=1.2, label=f"train, mean of {k}")
    if val:
        ax.plot(*np.array(val).T, "o-", color="C3", label="validation (scenes: metrics.jsonl)")
    for i, step in enumerate(restarts):
        ax.axvline(step, color="0.4", ls="--", lw=0.8, label="resumed, new schedule" if i == 0 else None)
    for step, views in view_changes:
        ax.axvline(step, color="C2", ls=":", lw=1.0,
                   label=f"from here K drawn from [{views[0]}, {views[1]}]" if views else "from here the preset's K")
    ax.set_xlabel("step")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, format="png")
    plt.close(fig)


def encoder_card(model_config: dict) -> dict:
    """The image encoder of a checkpoint and where its weights come from (origin and licence)."""
    from omnirecon.models.pretrained import ORIGIN

    name = model_config.get("encoder", "scratch")
    return {"name": name, "origin": ORIGIN[name]}


def ship(model: str, run: Path, cpu_budget: float, threads: int, steps: int, dest: Path | None = None) -> Path:
    """Copy the final checkpoint to checkpoints/<model>/ (or ``dest``) and write its model card (with the run's
    ``notes.md``, when it has one, as a paragraph)."""
    dest = dest or ROOT / "checkpoints" / model
    final = run / "checkpoints" / "final"
    meta = json.loads((final / "meta.json").read_text())
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]
    train_rows = [r for r in rows if "loss" in r]
    val_rows = [r for r in rows if any(k.startswith("val") for k in r)]
    parent = parent_card(run)
    base_steps = parent.get("steps", 0) if parent else 0
    base_cpu = parent.get("cpu_seconds", 0.0) if parent else 0.0
    stages_file = run / "stages.json"
    stages = json.loads(stages_file.read_text()) if stages_file.is_file() else []
    real_weight = float(stages[-1].get("real_weight", 1.0)) if stages else 1.0
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for name in ("model.safetensors", "meta.json"):
        shutil.copy2(final / name, tmp / name)
    card = {
        "model": model, "steps": base_steps + meta["step"], "cpu_seconds": base_cpu + meta["extra"].get("cpu_s", 0.0),
        "wall_seconds": (parent.get("wall_seconds") or 0.0 if parent else 0.0) + meta["extra"].get("elapsed_s", 0.0),
        "cpu_budget_s": (parent.get("cpu_budget_s") or 0.0 if parent else 0.0) + cpu_budget, "threads": threads,
        "resolution": RESOLUTION, "seed": SEED,
        "data": {"procedural": SYNTH, "real": REAL, "weights": weights(real_weight)},
        **({"warm_start": {"from": parent["init"], "steps": base_steps, "cpu_seconds": base_cpu,
                           "stages": parent.get("stages"), "stage_spans": parent.get("stage_spans"),
                           "data": parent.get("data"), "curve": parent.get("curve")}} if parent else {}),
        "held_out": "procedural seeds 900000-900999, dtu_scan24, dtu_scan37, fern (never trained on)",
        "command": " && ".join(stage_commands(model, run, cpu_budget, steps, threads)),
        "stages": stage_commands(model, run, cpu_budget, steps, threads),
        "stage_spans": stage_spans(run, train_rows, meta["step"]),
        "train_psnr_last": train_rows[-1]["psnr"] if train_rows else None,
        "train_psnr_first": train_rows[0]["psnr"] if train_rows else None,
        "validation": val_rows[-1] if val_rows else None,
        "model_config": meta["model_config"], "provenance": meta.get("provenance", {}),
        "encoder": encoder_card(meta["model_config"]),
    }
    card["curve"] = {"train": [[r["step"], round(r["psnr"], 3)] for r in train_rows[::10]],
                     "validation": [[r["step"], round(r["val_psnr"], 3)] for r in rows if "val_psnr" in r]}
    restarts = [st["from_step"] + base_steps for prev, st in zip(stages, stages[1:]) if st["steps"] != prev["steps"]]
    view_changes = [(st["from_step"] + base_steps, st.get("num_views_range")) for prev, st in zip(stages, stages[1:])
                    if st.get("num_views_range") != prev.get("num_views_range")]
    shifted = [{**r, "step": r["step"] + base_steps} for r in rows]
    plot_curve(shifted, tmp / "training_curve.png",
               f"{model}: {card['steps']} steps, {card['cpu_seconds']:.0f} CPU-s", restarts, view_changes,
               before=parent.get("curve") if parent else None, warm_at=base_steps if parent else None)
    (tmp / "card.json").write_text(json.dumps(card, indent=1))
    (tmp / "MODEL_CARD.md").write_text("\n".join([
        f"# {model}", "",
        f"Trained (seed {SEED}) for {card['steps']} steps in {card['cpu_seconds']:.0f} CPU seconds "
        f"({card['wall_seconds']:.0f} s wall, {threads} thread) at {RESOLUTION}x{RESOLUTION} by", "",
        *[f"{i + 1}. `{c}`" + (f" (steps {sp['from_step']}-{sp['to_step']}, {sp['cpu_s']:.0f} CPU-s)" if sp else "")
          for i, (c, sp) in enumerate(parent_stages(parent))],
        *[f"{i + 1 + len(parent_stages(parent))}. `{c}` (steps {sp['from_step'] + base_steps}-{sp['to_step'] + base_steps}"
          f", {sp['cpu_s']:.0f} CPU-s)" for i, (c, sp) in enumerate(zip(card["stages"], card["stage_spans"]))], "",
        *([f"Stages 1-{len(parent_stages(parent))} made the checkpoint shipped before (its card: steps 0-{base_steps}, "
           f"{base_cpu:.0f} CPU-s, run in `outputs/train/{model}_bench`). Stage {len(parent_stages(parent)) + 1} is a "
           f"warm start from it (`--init`: its weights, a fresh optimizer, a new learning-rate schedule and data mix; "
           f"dashed line on the curve) in the run `outputs/train/{run.name}`; the card's steps and CPU seconds are "
           "the sums of both.", ""] if parent else []),
        *(["Each later command resumes the run (`--resume`, exact optimizer and RNG state). Where it names a different "
           "`--steps` the cosine schedule is recomputed for the new length from where it starts (the learning rate "
           "rises again after an annealed stage: a warm restart; each change is marked on the curve); with the same "
           "`--steps` it finishes the schedule an earlier `--stop-at` cut short."
           + (" A command with `--num-views-range LO HI` draws the number of source views K from [LO, HI] at every "
              "step from there on (dotted line on the curve); the others use the preset's K = "
              f"{meta['model_config'].get('num_views')}." if view_changes else "")]
          if len(card["stages"]) > 1 else []), "",
        "Data: procedural scenes of the object, frontal and forward rigs (training seeds drawn from 0-899999) and the "
        "real training scenes " + ", ".join(REAL) + f" with mixing weights {card['data']['weights']}"
        + (f" (the warm-start checkpoint's run: {parent['data']['weights']})" if parent and parent.get("data") else "")
        + f". Held out: {card['held_out']}.", "",
        f"Image encoder (`encoder={card['encoder']['name']}`): {card['encoder']['origin']}"
        + (" (origin and licence: docs/pretrained.md)." if card["encoder"]["name"] != "scratch" else "."), "",
        f"Training PSNR (sampled rays) {card['train_psnr_first']:.2f} dB at the first log step -> "
        f"{card['train_psnr_last']:.2f} dB at the last. Last validation (monitoring only: a run ships its final "
        f"checkpoint, never an intermediate one picked by validation): {json.dumps(card['validation'])}.", "",
        *([(run / "notes.md").read_text().strip(), ""] if (run / "notes.md").is_file() else []),
        "Evaluation numbers are in BENCHMARKS.md (`python -m bench quality`). Files: model.safetensors (weights), "
        "meta.json (preset, config, step), card.json (this card as data, with the training curve), "
        "training_curve.png.", "", "![training curve](training_curve.png)", ""]))
    shutil.rmtree(dest, ignore_errors=True)
    tmp.rename(dest)
    return dest


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="gpnr-tiny")
    p.add_argument("--cpu-budget", type=float, default=1800.0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--synth-scenes", type=int, default=32)
    p.add_argument("--steps", type=int, default=3000, help="length of the learning-rate schedule")
    p.add_argument("--stop-at", type=int, default=None,
                   help="end the run at this step (the schedule stays --steps long); resumes a longer run's checkpoint")
    p.add_argument("--num-views-range", type=int, nargs=2, default=None, metavar=("LO", "HI"),
                   help="draw the source-view count K uniformly from [LO, HI] at every step (default: the preset's)")
    p.add_argument("--encoder", default="scratch", choices=["scratch", "vgg16", "alexnet"],
                   help="image encoder (docs/pretrained.md): the model's own from scratch, or a frozen pretrained one")
    p.add_argument("--init", type=Path, default=None,
                   help="warm start from this checkpoint folder's weights (fresh optimizer and schedule)")
    p.add_argument("--lr", type=float, default=None, help="peak learning rate (default: the family's, 5e-4)")
    p.add_argument("--warmup", type=int, default=None, help="warm-up steps (default: 100)")
    p.add_argument("--real-weight", type=float, default=None,
                   help="mixing weight of each real training scene (default 1; the procedural rigs keep 2)")
    p.add_argument("--prepare", action="store_true", help="only generate the procedural scenes")
    p.add_argument("--run-name", default=None,
                   help="run folder under outputs/train (default: <model>_bench, the shipped checkpoint's run)")
    p.add_argument("--no-ship", action="store_true",
                   help="leave checkpoints/<model>/ alone (a candidate run: ship it with --reship once validation "
                        "says it is better)")
    p.add_argument("--reship", action="store_true",
                   help="only rewrite checkpoints/<model>/ (card, curve) from the finished run in outputs/train")
    a = p.parse_args(argv)
    if a.reship:
        run = ROOT / "outputs" / "train" / (a.run_name or f"{a.model}_bench")
        print(f"shipped {ship(a.model, run, a.cpu_budget, a.threads, a.steps)}")
        return
    prepare(a.synth_scenes)
    if a.prepare:
        return
    overrides = [f"encoder={a.encoder}"] if a.encoder != "scratch" else []
    run = train(a.model, a.cpu_budget, a.threads, a.synth_scenes, a.steps, overrides, name=a.run_name,
                stop_at=a.stop_at, views=tuple(a.num_views_range) if a.num_views_range else None,
                tune=dict(init=a.init, lr=a.lr, warmup=a.warmup, real_weight=a.real_weight))
    if a.no_ship:
        print(f"trained {run} (not shipped: --no-ship)")
        return
    print(f"shipped {ship(a.model, run, a.cpu_budget, a.threads, a.steps)}")

