"""Training levers at a small fixed CPU budget: each lever against its baseline, same seed, data, schedule and
budget (process CPU seconds, 1 thread), one run at a time. Scored on validation data only: procedural
validation seeds (901000+) and the held-out views of the real training scenes (the test split / every 8th
view, which training never draws). The final held-out scenes (fern, dtu_scan24/37, seeds 900000+) are not
looked at here.

    python -m bench train_levers --runs ibrnet_vgg16 gpnr_vgg16 gpnr_scratch --cpu-budget 100
    python -m bench train_levers --eval-only --runs ibrnet_vgg16       # rescore finished runs, rewrite the JSON
    python -m bench train_levers --eval-only --runs ibrnet_vgg16 --shipped ibrnet-tiny   # also score a shipped checkpoint

Every run: ``--schedule constant --warmup 50`` (a run cut by its CPU budget is at the same point of the
schedule as its rival whatever its cost per step), K drawn from [3, 10], 8 procedural scenes per rig and the
real training scenes. Runs live in outputs/train/lever_<name>; results go to bench/results/train_levers.json
(provenance header; the table: `python -m bench page --reuse`).
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
from pathlib import Path

from bench.train_tiny import CACHE, REAL, SEED, SHARED

ROOT = Path(__file__).resolve().parents[1]

SYNTH = ["object", "frontal", "forward"]
SYNTH_SCENES = 8
BASE_WEIGHTS = [2.0, 2.0, 2.0] + [1.0] * len(REAL)
VAL_SCENES = {"object": (901000,), "frontal": (901002,), "forward": (901004,)}
"""Procedural validation seeds, one per rig (never trained on, never the evaluation seeds 900000+; few, for the
CPU: scoring one run costs about as much as training it)."""
REALISM = dict(specular=0.4, light_variation=1.0, noise=0.02, exposure=0.3, white_balance=0.05, vignetting=0.3, blur=0.6)
"""``omnirecon synth`` realism options of the realism lever (the values its help suggests)."""

LEVERS: dict[str, dict] = {
    "ibrnet_vgg16": dict(model="ibrnet-tiny", encoder="vgg16", base=None,
                         what="ibrnet-tiny + frozen VGG16 (baseline of the data, loss and resolution levers)"),
    "gpnr_scratch": dict(model="gpnr-tiny", encoder="scratch", base=None, what="gpnr-tiny, encoder from scratch"),
    "gpnr_vgg16": dict(model="gpnr-tiny", encoder="vgg16", base="gpnr_scratch", what="gpnr-tiny + frozen VGG16"),
    "omnirecon_scratch": dict(model="omnirecon-tiny", encoder="scratch", base=None,
                              what="omnirecon-tiny, encoder from scratch"),
    "omnirecon_vgg16": dict(model="omnirecon-tiny", encoder="vgg16", base="omnirecon_scratch",
                            what="omnirecon-tiny + frozen VGG16"),
    "ibrnet_vgg16_depth": dict(model="ibrnet-tiny", encoder="vgg16", base="ibrnet_vgg16", depth_weight=0.1,
                               what="+ exact depth on procedural scenes (--depth-weight 0.1)"),
    "ibrnet_vgg16_stereo": dict(model="ibrnet-tiny", encoder="vgg16", base="ibrnet_vgg16_depth", depth_weight=0.1,
                                stereo_depth=True,
                                what="+ confident stereo depth as pseudo-GT on the real scenes (--stereo-depth)"),
    "ibrnet_vgg16_realism": dict(model="ibrnet-tiny", encoder="vgg16", base="ibrnet_vgg16", realism=True,
                                 what="+ synth realism (specular, light, noise, exposure, WB, vignetting, blur)"),
    "ibrnet_vgg16_real3": dict(model="ibrnet-tiny", encoder="vgg16", base="ibrnet_vgg16", real_weight=3.0,
                               what="real-scene weight 1 -> 3 (procedural 2 per rig)"),
    "ibrnet_vgg16_64to128": dict(model="ibrnet-tiny", encoder="vgg16", base="ibrnet_vgg16", fork=0.5, resolution=128,
                                 what="first half of the budget at 64 px (the baseline's), second half at 128 px"),
}


def run_dir(name: str) -> Path:
    return ROOT / "outputs" / "train" / f"lever_{name}"


def synth_refs(resolution: int) -> list:
    from omnirecon.data.bank import parse_sources

    return parse_sources([f"synth:{r}:{SYNTH_SCENES}" for r in SYNTH], "train", seed=SEED, synth_scenes=SYNTH_SCENES,
                         cache=CACHE, resolution=resolution, synth_views=40)


def prepare(resolution: int, realism: bool) -> list[Path]:
    """Generate the procedural training scenes (before the clock starts); with ``realism`` the same seeds with
    the realism options, in their own folder (one folder per rig, passed as data)."""
    from omnirecon.data.synth.generate import SynthOptions, generate_scene

    folders = []
    for rig, refs in zip(SYNTH, synth_refs(resolution)):
        folder = CACHE.parent / "synth_realism" / f"{rig}_{resolution}" if realism else refs[0].path.parent
        for r in refs:
            if not (folder / r.path.name).is_dir():
                generate_scene(folder, r.seed, SynthOptions(rig=rig, views=40, resolution=resolution,
                                                            **(REALISM if realism else {})))
        folders.append(folder)
    return folders


def data_args(lever: dict) -> list[str]:
    real = [str(SHARED / r) for r in REAL if (SHARED / r).is_dir()]
    synth = [str(f) for f in prepare(64, True)] if lever.get("realism") else \
        [f"synth:{r}:{SYNTH_SCENES}" for r in SYNTH]
    weights = [2.0] * len(synth) + [lever.get("real_weight", 1.0)] * len(real)
    return ["--data", *synth, *real, "--data-weights", *map(str, weights)]


def train_cmd(name: str, budget: float, resolution: int = 64) -> list[str]:
    lever = LEVERS[name]
    cmd = [sys.executable, "-m", "omnirecon.cli", "train", "--model", lever["model"], *data_args(lever),
           "--resolution", str(resolution), "--steps", "100000", "--schedule", "constant", "--warmup", "50",
           "--num-views-range", "3", "10", "--cpu-budget", str(budget), "--threads", "1", "--seed", str(SEED),
           "--synth-scenes", str(SYNTH_SCENES), "--cache", str(CACHE), "--val-every", "0", "--ckpt-every", "0",
           "--out", str(run_dir(name)), "--no-progress"]
    if lever["encoder"] != "scratch":
        cmd += ["--model-overrides", f"encoder={lever['encoder']}"]
    if "depth_weight" in lever:
        cmd += ["--depth-weight", str(lever["depth_weight"])]
    if lever.get("stereo_depth"):
        cmd.append("--stereo-depth")
    if (run_dir(name) / "checkpoints" / "latest").exists():
        cmd.append("--resume")
    return cmd


def run(cmd: list[str], log: Path) -> None:
    print(" ".join(cmd), flush=True)
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as f:
        subprocess.run(cmd, check=True, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT)


def train(name: str, budget: float) -> None:
    """Train one lever run to ``budget`` CPU-s. A ``fork`` lever copies its baseline's checkpoint at
    ``fork x budget`` (the baseline is trained to that point first) and continues it at its own resolution."""
    lever = LEVERS[name]
    out = run_dir(name)
    final = out / "checkpoints" / "final"
    if final.is_dir() and json.loads((final / "meta.json").read_text())["extra"]["cpu_s"] >= budget - 1:
        return
    if lever.get("resolution", 64) != 64:
        prepare(lever["resolution"], bool(lever.get("realism")))
    if lever.get("fork") and not (out / "checkpoints").is_dir():
        shutil.copytree(fork_point(lever["base"], lever["fork"] * budget), out, symlinks=True)
    forks = [f for f, lv in LEVERS.items() if lv.get("base") == name and lv.get("fork")]
    for f in forks:  # the forks' starting point, before this run goes past it
        fork_point(name, LEVERS[f]["fork"] * budget)
    run(train_cmd(name, budget, lever.get("resolution", 64)), out.with_suffix(".log"))


def cpu_s(run: Path) -> float:
    latest = run / "checkpoints" / "latest"
    return json.loads((latest / "meta.json").read_text())["extra"]["cpu_s"] if latest.exists() else 0.0


def fork_point(name: str, at: float) -> Path:
    """A copy of run ``name`` at ``at`` CPU-s (trained there first), kept as outputs/train/lever_<name>_at<at>."""
    snap = run_dir(name).with_name(f"lever_{name}_at{at:g}")
    if not snap.is_dir():
        if cpu_s(run_dir(name)) > at + 1:
            raise SystemExit(f"{run_dir(name)} is past {at:g} CPU-s: delete it, or the fork, and rerun")
        run(train_cmd(name, at), run_dir(name).with_suffix(".log"))
        shutil.copytree(run_dir(name), snap, symlinks=True)
    return snap


def val_scenes() -> list[str]:
    from omnirecon.data.synth.generate import SynthOptions, generate_scene

    out = []
    for rig, seeds in VAL_SCENES.items():
        for seed in seeds:
            out.append(str(generate_scene(ROOT / "outputs" / "cache" / "lever_val" / rig, seed,
                                          SynthOptions(rig=rig, views=40, resolution=64))))
    return out + [str(SHARED / r) for r in REAL if (SHARED / r).is_dir()]


def evaluate(ckpt: Path, out: Path, ks: list[str]) -> dict:
    """``omnirecon eval`` (cpu protocol, K in ``ks``) on the validation scenes; PSNR per scene and K. Reuses earlier
    scores of the same checkpoint (folders ``<out>_k...``) and evaluates only the K none of them has."""
    done: dict[str, Path] = {}
    for d in [out, *sorted(out.parent.glob(out.name + "_k*"))]:  # <out> itself: folders named by older code
        if (d / "results.json").is_file():
            for k in json.loads((d / "results.json").read_text())["num_views"]:
                done.setdefault(str(k), d)
    missing = [k for k in ks if k not in done]
    if missing:
        new = out.with_name(f"{out.name}_k{'_'.join(missing)}")
        cmd = [sys.executable, "-m", "omnirecon.cli", "eval", "--ckpt", str(ckpt), "--scenes", *val_scenes(),
               "--protocol-set", "cpu", "--num-views", *missing, "--threads", "1", "--out", str(new), "--no-save-images"]
        t = resource.getrusage(resource.RUSAGE_CHILDREN).ru_utime
        run(cmd, new.with_suffix(".log"))
        print(f"  eval {resource.getrusage(resource.RUSAGE_CHILDREN).ru_utime - t:.0f} CPU-s", flush=True)
        done.update({k: new for k in missing})
    scenes: dict = {}
    load = None
    for k in ks:
        res = json.loads((done[k] / "results.json").read_text())
        load = res.get("provenance", {}).get("loadavg_1min")
        for s in res["scenes"]:
            key = f"synth:{s['name']}" if s["name"].startswith("scene_") else s["name"]
            if k in s["settings"]:
                scenes.setdefault(key, {})[k] = round(s["settings"][k]["mean"]["psnr"], 3)
    return {"scenes": scenes, "load": load}


def summarize(scenes: dict) -> dict:
    """Mean PSNR over the procedural validation scenes and over the real scenes, per K (scenes outside the current
    validation set, e.g. from an older set, are left out)."""
    keep = {f"synth:scene_{s:05d}" for seeds in VAL_SCENES.values() for s in seeds} | {Path(r).name for r in REAL}
    scenes = {n: v for n, v in scenes.items() if n in keep}
    out = {}
    for group, pick in (("procedural", lambda n: n.startswith("synth:")), ("real", lambda n: not n.startswith("synth:"))):
        for k in ("3", "10"):
            vals = [v[k] for n, v in scenes.items() if pick(n) and k in v]
            out[f"{group}_{k}"] = round(sum(vals) / len(vals), 3) if vals else None
    return out


def row(name: str, ks: list[str]) -> dict:
    final = run_dir(name) / "checkpoints" / "final"
    meta = json.loads((final / "meta.json").read_text())
    ev = evaluate(final, run_dir(name) / "eval_val", ks)
    return {"what": LEVERS[name]["what"], "base": LEVERS[name]["base"], "model": LEVERS[name]["model"],
            "step": meta["step"], "cpu_s": round(meta["extra"]["cpu_s"], 1), "command": " ".join(
                train_cmd(name, 0)[1:]).replace("--cpu-budget 0", "--cpu-budget B").replace(" --resume", ""),
            **ev, **summarize(ev["scenes"])}


def shipped_row(model: str, ks: list[str]) -> dict:
    ckpt = ROOT / "checkpoints" / model
    card = json.loads((ckpt / "card.json").read_text()) if (ckpt / "card.json").is_file() else {}
    ev = evaluate(ckpt, ROOT / "outputs" / "train" / "lever_shipped" / model, ks)
    return {"what": f"shipped {model}", "model": model, "step": card.get("steps"), "cpu_s": card.get("cpu_seconds"),
            **ev, **summarize(ev["scenes"])}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", nargs="*", default=list(LEVERS), choices=list(LEVERS),
                   help="lever runs to train and score (none: `--runs` alone, e.g. to score only --shipped / --extra)")
    p.add_argument("--cpu-budget", type=float, default=100.0)
    p.add_argument("--eval-only", action="store_true", help="score finished runs only")
    p.add_argument("--num-views", nargs="+", default=["3"],
                   help="K scored (scoring costs about as much CPU as a 100-CPU-s run per K: 3 only by default)")
    p.add_argument("--shipped", nargs="*", default=None, help="also score these shipped checkpoints")
    p.add_argument("--extra", nargs="*", default=[], metavar="NAME=CKPT",
                   help="also score other checkpoints (e.g. a continued run) under a name")
    a = p.parse_args(argv)
    dest = ROOT / "bench" / "results" / "train_levers.json"
    result = json.loads(dest.read_text()) if dest.is_file() else {"runs": {}, "shipped": {}, "extra": {}}
    for name in a.runs:
        if not a.eval_only:
            train(name, a.cpu_budget)
        if (run_dir(name) / "checkpoints" / "final").is_dir():
            result["runs"][name] = row(name, a.num_views)
            save(result, dest, a.cpu_budget)
    for model in a.shipped or []:
        result["shipped"][model] = shipped_row(model, a.num_views)
        save(result, dest, a.cpu_budget)
    for item in a.extra:
        name, ckpt = item.split("=", 1)
        meta = json.loads((Path(ckpt) / "meta.json").read_text())
        ev = evaluate(Path(ckpt), ROOT / "outputs" / "train" / "lever_extra" / name, a.num_views)
        result["extra"][name] = {"checkpoint": ckpt, "step": meta["step"], "cpu_s": meta["extra"].get("cpu_s"),
                                 **ev, **summarize(ev["scenes"])}
        save(result, dest, a.cpu_budget)
    result["curves"] = curves_figure(ROOT / "bench" / "results" / "figures" / "levers_ibrnet_curves.png",
                                     result.get("curves"))
    save(result, dest, a.cpu_budget)
    for group in ("runs", "shipped", "extra"):
        for name, r in result.get(group, {}).items():
            print(f"{name}: step {r.get('step')}, procedural K=3 {r.get('procedural_3')}, real K=3 {r.get('real_3')}")
    print(f"wrote {dest} (the table: python -m bench page --reuse)")


def save(result: dict, dest: Path, budget: float) -> None:
    from omnirecon.provenance import provenance

    result.update(provenance=provenance(SEED), cpu_budget=budget, val_scenes={k: list(v) for k, v in VAL_SCENES.items()},
                  real_val=REAL, realism=REALISM)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1, default=str))
    tmp.replace(dest)


def curves_figure(dest: Path, previous: dict | None = None) -> dict:
    """Monitoring validation PSNR (seeds 901000-901001, the runs' own ``val_psnr``) against CPU-s: ibrnet-tiny with
    its encoder from scratch and the continued ibrnet-tiny + VGG16 run, for the next-budget estimate. CPU-s of the
    scratch run: its steps times its mean CPU-s per step (the card keeps no per-step CPU). Since the VGG16 run
    shipped (2026-11-24) the scratch curve comes from the ``previous`` results (the curve drawn while it shipped)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    card = json.loads((ROOT / "checkpoints" / "ibrnet-tiny" / "card.json").read_text())
    if card.get("encoder", {}).get("name", "scratch") == "scratch":
        per_step = card["cpu_seconds"] / card["steps"]
        shipped, steps = [(s * per_step, v) for s, v in card["curve"]["validation"]], card["steps"]
    else:  # the shipped checkpoint is the VGG16 run itself: keep the scratch run's curve as last drawn
        shipped, steps = [tuple(x) for x in (previous or {}).get("shipped_ibrnet_tiny", [])], 7000
    rows = [json.loads(x) for x in (ROOT / "checkpoints" / "runs" / "ibrnet-tiny_vgg16" / "metrics.jsonl")
            .read_text().splitlines() if x.strip()]
    cpu = {r["step"]: r["cpu_time"] for r in rows if "cpu_time" in r}
    vgg = [(cpu.get(r["step"]), r["val_psnr"]) for r in rows if "val_psnr" in r and r["step"] in cpu]
    fig, ax = plt.subplots(figsize=(5.5, 3.3), dpi=120)
    if shipped:
        ax.plot(*zip(*shipped), "o-", color="0.4", label=f"ibrnet-tiny, scratch encoder (shipped until 2026-11-24), {steps} steps")
    ax.plot(*zip(*vgg), "s-", color="C3", label="ibrnet-tiny + frozen VGG16 (shipped since 2026-11-24)")
    ax.set_xscale("log")
    ticks = [200, 500, 1000, 2000, 5000]
    ax.set_xticks(ticks, [str(t) for t in ticks])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("training CPU-seconds (1 thread)")
    ax.set_ylabel("validation PSNR (dB), seeds 901000-1")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    dest.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(dest, format="png")
    plt.close(fig)
    return {"shipped_ibrnet_tiny": [[round(c), round(v, 2)] for c, v in shipped],
            "ibrnet_tiny_vgg16": [[round(c), round(v, 2)] for c, v in vgg], "figure": str(dest.relative_to(ROOT))}
