"""A shipped tiny checkpoint trained further at the size users see (256 px), chosen on validation only.

    python -m bench train_256 --train --cpu-budget 3600        # the warm start (resumes; 1 thread, niced by the caller)
    python -m bench train_256                                  # score the shipped checkpoint and the run's final state
    python -m bench train_256 --mix 64 --train --steps 1400    # the same with half the scenes read at 64 px

The shipped checkpoints were trained at 64 px; the 256-px protocol sets score them at 4x that size, where their image
encoder sees finer detail than it was trained with. This continues ``checkpoints/<model>`` (``--init``: fresh
optimizer, peak lr 1e-4 after 20 warm-up steps, cosine over ``--steps``) on the shipped data mix read at 256 px
(procedural rigs at weight 2, ``--synth-scenes`` scenes each, generated at 256 px; the real training scenes at 1), K
as the checkpoint was trained (ibrnet-tiny, gpnr-tiny: drawn from [3, 10]; omnirecon-tiny: its preset's 4), seed 0,
for ``--cpu-budget`` process CPU-seconds. With ``--mix R``, half the scenes drawn are read at ``R`` px instead
(``omnirecon train --mix-resolution R --mix-share 0.5``: one run at both sizes), into its own run folder and results
file.

Both checkpoints are scored on validation data only (the final held-out scenes, fern, dtu_scan24/37 and the
evaluation seeds, are not looked at): ``omnirecon eval`` with K = 3 at 256 px (``--protocol-set cpu256``, full
sampling) and at 64 px (``--protocol-set cpu``, the size the checkpoint was chosen at), on the procedural validation
seeds 901000, 901002 and 901004 (one per rig, generated at the set's size) and the held-out views of the real training
scenes. Whole-image PSNR (dB), the mean per group. The rule (:func:`decide`): a run that beats the shipped weights by
more than :data:`MARGIN_DB` on both groups at 256 px and loses at most :data:`MARGIN_DB` on either at 64 px replaces
them; one that beats them at 256 px but loses at 64 px ships as the checkpoint's 256-px weights
(``checkpoints/<model>/sizes/256/``: ``eval``, ``render`` and the demo load the weights trained nearest the size they
render at, so the 64-px weights stay where they score best); otherwise nothing ships. ``--full-render`` and
``--samples N`` add candidates for the 256-px weights: both states rendered at 256 px with every render option at its
full-render value, or with N samples per ray and the shipped checkpoint's other render options (more depth steps
across the 4x wider disparity range in pixels). This module reports the decision
and, with ``--ship``, carries it out (:func:`ship`). The shipped row is always the checkpoint's own weights
(``sizes/`` apart: :func:`own_weights`), so a rerun after shipping compares the same two states.

Writes ``bench/results/train_256.json`` for ibrnet-tiny, ``train_256_<model>.json`` for the others (with ``--mix R``:
``train_256_mix<R>.json``, for the others ``train_256_mix<R>_<model>.json``).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
from pathlib import Path

from bench.train_levers import VAL_SCENES
from bench.train_tiny import REAL, SEED, SHARED, WEIGHTS

ROOT = Path(__file__).resolve().parents[1]
SIZE = 256
MARGIN_DB = 0.1
"""PSNR (dB) by which the run must beat the shipped checkpoint on both validation groups at 256 px (and may lose at
most at 64 px)."""
SETS = {"256": "cpu256", "64": "cpu"}
"""Long side (px) -> the protocol set scoring at that size."""


def run_dir(model: str, mix: int = 0) -> Path:
    return ROOT / "outputs" / "train" / (f"{model}_256_mix{mix}" if mix else f"{model}_256_ft")


def train_cmd(model: str, cpu_budget: float, steps: int, synth_scenes: int, mix: int = 0) -> list[str]:
    """The warm start's ``omnirecon train`` command (with ``--resume`` where an interrupted run left a checkpoint;
    ``mix``: half the scenes at that size)."""
    real = [str(SHARED / r) for r in REAL if (SHARED / r).is_dir()]
    card = json.loads((ROOT / "checkpoints" / model / "card.json").read_text())
    encoder = card.get("encoder", {}).get("name", "scratch")
    views = json.loads((ROOT / "checkpoints" / model / "meta.json").read_text())["train_config"].get("num_views_range")
    views = ["--num-views-range", *map(str, views)] if views else []  # as the checkpoint was trained: K drawn, or fixed
    return [sys.executable, "-m", "omnirecon.cli", "train", "--model", model,
            *(["--model-overrides", f"encoder={encoder}"] if encoder != "scratch" else []),
            "--init", str(ROOT / "checkpoints" / model),
            "--data", "synth:object", "synth:frontal", "synth:forward", *real,
            "--data-weights", *map(str, WEIGHTS[:3 + len(real)]), "--synth-scenes", str(synth_scenes),
            "--cache", str(ROOT / "outputs" / "cache" / f"synth{SIZE}"), "--resolution", str(SIZE),
            "--steps", str(steps), "--cpu-budget", str(cpu_budget), "--threads", "1", "--seed", str(SEED),
            "--lr", "1e-4", "--warmup", "20", *views, "--val-every", "0",
            *(["--mix-resolution", str(mix), "--mix-share", "0.5"] if mix else []),
            "--ckpt-every", "250", "--keep", "2", "--log-every", "10", "--no-progress", "--out", str(run_dir(model, mix)),
            *(["--resume"] if (run_dir(model, mix) / "checkpoints" / "latest").exists() else [])]


def val_scenes(size: int) -> list[str]:
    """The procedural validation seeds generated at ``size`` px, then the real training scenes (their held-out
    views are the targets)."""
    from omnirecon.data.synth.generate import SynthOptions, generate_scene

    out = [str(generate_scene(ROOT / "outputs" / "cache" / f"val{size}" / rig, seed,
                              SynthOptions(rig=rig, views=40, resolution=size)))
           for rig, seeds in VAL_SCENES.items() for seed in seeds]
    return out + [str(SHARED / r) for r in REAL if (SHARED / r).is_dir()]


def score(ckpt: Path, out: Path, size: str) -> dict:
    """``omnirecon eval`` of ``ckpt`` (K = 3, the set of ``size``) on the validation scenes, kept in ``out`` (an
    existing result is reused): ``{"scenes": {name: PSNR}, "procedural", "real": group means, "cpu_s", "load"}``."""
    if not (out / "results.json").is_file():
        cmd = [sys.executable, "-m", "omnirecon.cli", "eval", "--ckpt", str(ckpt), "--scenes", *val_scenes(int(size)),
               "--protocol-set", SETS[size], "--num-views", "3", "--threads", "1", "--out", str(out),
               "--no-save-images"]
        before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_utime
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        (out / "cpu_s.txt").write_text(f"{resource.getrusage(resource.RUSAGE_CHILDREN).ru_utime - before:.1f}\n")
    res = json.loads((out / "results.json").read_text())
    scenes = {(f"synth:{s['name']}" if s["name"].startswith("scene_") else s["name"]):
              round(s["settings"]["3"]["mean"]["psnr"], 3) for s in res["scenes"]}
    groups = {g: [v for n, v in scenes.items() if n.startswith("synth:") == (g == "procedural")]
              for g in ("procedural", "real")}
    cpu = out / "cpu_s.txt"
    return {"scenes": scenes, **{g: round(sum(v) / len(v), 3) for g, v in groups.items()},
            "cpu_s": float(cpu.read_text()) if cpu.is_file() else None,
            "load": res.get("provenance", {}).get("loadavg_1min")}


def gains(shipped: dict, run: dict) -> dict[str, float]:
    """The run's PSNR minus the shipped checkpoint's, per group and size (dB)."""
    return {f"{g} {s} px": round(run[s][g] - shipped[s][g], 3) for s in SETS for g in ("procedural", "real")}


def decide(shipped: dict, run: dict, full: list[dict] = ()) -> tuple[str | None, str]:
    """Where the run ships (module docstring): ``("replace", why)``, ``("sizes", why)`` or ``(None, why)``, from the
    two rows' scores (the gains: :func:`gains`); with ``full`` (the 256-px rows rendered with every render option at
    its full-render value, or with N samples per ray: ``--samples``), ``("sizes:<row name>", why)`` when one of those
    beats both the shipped checkpoint and the run by more than :data:`MARGIN_DB` on both groups at 256 px (the best by
    the mean of the two)."""
    gain = gains(shipped, run)
    better = all(gain[f"{g} 256 px"] > MARGIN_DB for g in ("procedural", "real"))
    kept = all(gain[f"{g} 64 px"] >= -MARGIN_DB for g in ("procedural", "real"))

    def beats(row: dict, base: dict) -> bool:
        return all(row["256"][g] - base["256"][g] > MARGIN_DB for g in ("procedural", "real"))

    wins = [row for row in full if beats(row, shipped) and (not better or beats(row, run))]
    if wins:
        best = max(wins, key=lambda row: row["256"]["procedural"] + row["256"]["real"])
        return f"sizes:{best['name']}", (f"ships {best['name']} as the checkpoint's {SIZE}-px weights (beats the "
                                          f"shipped checkpoint{' and the run' if better else ''} by more than "
                                          f"{MARGIN_DB:g} dB on both groups at {SIZE} px; the checkpoint's own "
                                          "weights and render options stay at 64 px)")
    if better and kept:
        return "replace", "ships (replaces the checkpoint's weights)"
    if better:
        return "sizes", (f"ships as the checkpoint's {SIZE}-px weights (beats the shipped checkpoint at {SIZE} px, "
                         f"loses more than {MARGIN_DB:g} dB at 64 px, where the checkpoint's own weights stay)")
    return None, f"not shipped (does not beat the shipped checkpoint by more than {MARGIN_DB:g} dB on both groups at {SIZE} px)"


def own_weights(model: str) -> Path:
    """A copy of ``checkpoints/<model>``'s own weights and meta.json without its ``sizes/`` (the shipped row: the state
    the run continued), refreshed when the weights change."""
    import shutil

    src, dest = ROOT / "checkpoints" / model, ROOT / "outputs" / "train" / "init" / f"{model}_own"
    if not (dest / "model.safetensors").is_file() or \
            (dest / "model.safetensors").read_bytes() != (src / "model.safetensors").read_bytes():
        shutil.rmtree(dest, ignore_errors=True)
        dest.mkdir(parents=True)
        for name in ("model.safetensors", "meta.json"):
            shutil.copy2(src / name, dest / name)
    return dest


def with_render(folder: Path, dest: Path, render: dict) -> Path:
    """A copy of checkpoint ``folder`` (its weights file and meta.json) at ``dest`` with the render options ``render``
    (:data:`~omnirecon.models.registry.RENDER_OPTIONS` keys) over its model config, refreshed when the weights
    change."""
    import shutil

    meta = json.loads((folder / "meta.json").read_text())
    meta["model_config"] = {**meta.get("model_config", {}), **render}
    if not (dest / "model.safetensors").is_file() or \
            (dest / "model.safetensors").read_bytes() != (folder / "model.safetensors").read_bytes():
        shutil.rmtree(dest, ignore_errors=True)
        dest.mkdir(parents=True)
        shutil.copy2(folder / "model.safetensors", dest / "model.safetensors")
    (dest / "meta.json").write_text(json.dumps(meta, indent=1))
    return dest


def samples_render(model: str, n: int) -> dict:
    """Render options of ``n`` samples per ray, every other render option as the shipped checkpoint has it (models
    whose config samples a ray once, ``render_samples``: gpnr-tiny)."""
    from omnirecon.models.registry import RENDER_OPTIONS

    config = json.loads((ROOT / "checkpoints" / model / "meta.json").read_text()).get("model_config", {})
    if "render_samples" not in config:
        raise SystemExit(f"--samples: {model} has no render_samples option (use --full-render)")
    return {**{k: v for k, v in config.items() if k in RENDER_OPTIONS}, "render_samples": n}


def full_render(folder: Path, dest: Path) -> Path:
    """:func:`with_render` with every render option of ``folder``'s config at its full-render value
    (:data:`~omnirecon.models.registry.RENDER_OPTIONS`: the samples the weights were trained with)."""
    from omnirecon.models.registry import RENDER_OPTIONS

    config = json.loads((folder / "meta.json").read_text()).get("model_config", {})
    return with_render(folder, dest, {k: v for k, v in RENDER_OPTIONS.items() if k in config})


def final_state(model: str, mix: int = 0) -> Path:
    """The run's final state as it is scored and shipped: its weights with the shipped checkpoint's render options
    (the :data:`~omnirecon.models.registry.RENDER_OPTIONS` keys of its model config, e.g. ibrnet-tiny's 16 + 16
    samples), so both rows render alike; a warm start's own meta.json keeps the preset's (the training samples).
    Written beside the run's ``checkpoints/`` as ``final_render/`` (:func:`with_render`)."""
    from omnirecon.models.registry import RENDER_OPTIONS

    shipped = json.loads((ROOT / "checkpoints" / model / "meta.json").read_text()).get("model_config", {})
    return with_render(run_dir(model, mix) / "checkpoints" / "final", run_dir(model, mix) / "final_render",
                       {k: v for k, v in shipped.items() if k in RENDER_OPTIONS})


def _card_stage(meta: dict, card: dict, result: dict, mix: int, own: bool = False) -> dict:
    """The card's record of a shipped 256-px stage; ``own``: the checkpoint's own weights with other render options
    (no training: no steps, no command)."""
    if own:
        return {"resolution": SIZE, "steps": 0, "cpu_seconds": 0.0, "wall_seconds": 0.0,
                "render": {k: v for k, v in meta.get("model_config", {}).items() if k.startswith("render_")},
                "from": {"steps": card["steps"], "cpu_seconds": card["cpu_seconds"]},
                "validation": {"rule": result["decision"], "rows": result["rows"]}}
    return {"resolution": SIZE, **({"mix_resolution": mix, "mix_share": 0.5} if mix else {}), "steps": meta["step"],
            "cpu_seconds": round(meta["extra"]["cpu_s"], 1), "wall_seconds": round(meta["extra"].get("elapsed_s", 0.0), 1),
            "command": result["command"], "from": {"steps": card["steps"], "cpu_seconds": card["cpu_seconds"]},
            "validation": {"rule": result["decision"], "rows": result["rows"]}}


def _card_text(stage: dict, meta: dict, card: dict, result: dict, mix: int, where: str) -> str:
    shipped, run = result["rows"][:2]
    run = next((r for r in result["rows"] if where.startswith("sizes:") and r["name"] == where[6:]), run)
    what = ("The card's steps and CPU seconds are the sums; the training curve above is the "
            f"{card['resolution']}-px run's." if where == "replace" else
            f"These weights are in `sizes/{SIZE}/` beside the checkpoint's own (only the tensors that differ, with "
            f"their render options in its meta.json{': every one at its full-render value' if run.get('render') == 'full' else ''}): "
            f"`eval`, `render` and the demo load the weights trained nearest the size they render at ({SIZE} px from a "
            "129-px long side up); the card's steps and CPU seconds are the own weights'.")
    if "render" in stage:  # the own weights with other render options: nothing trained
        options = ", ".join(f"`{k}={json.dumps(v)}`" for k, v in stage["render"].items())
        head = (f"## Rendered at {SIZE} px with other options", "",
                f"The checkpoint above (step {stage['from']['steps']}), its weights unchanged, renders from a 129-px long "
                f"side up with {options} (`sizes/{SIZE}/meta.json`; its `model.safetensors` holds no tensor, the own "
                f"weights serve): `eval`, `render` and the demo load these options at that size "
                "(`python -m bench train_256 --samples N`; nothing was trained).")
    else:
        head = (f"## Continued at {SIZE} px" + (f" and {mix} px" if mix else ""), "",
                f"The checkpoint above (step {stage['from']['steps']}, {stage['from']['cpu_seconds']:.0f} CPU-s) trained "
                f"{meta['step']} steps more at {SIZE} px{f' (half the scenes at {mix} px)' if mix else ''} in "
                f"{stage['cpu_seconds']:.0f} CPU-s (`python -m bench train_256`): `{result['command']}`. {what}")
    return "\n".join([
        *head, "",
        f"Validation (K = 3, whole-image PSNR, dB; procedural seeds / held-out views of the real training scenes): "
        f"at {SIZE} px {shipped['256']['procedural']:.2f} / {shipped['256']['real']:.2f} -> "
        f"{run['256']['procedural']:.2f} / {run['256']['real']:.2f}"
        + (f", at 64 px {shipped['64']['procedural']:.2f} / {shipped['64']['real']:.2f} -> {run['64']['procedural']:.2f}"
           f" / {run['64']['real']:.2f}" if "64" in run else f" ({run['name']}; at 64 px the own weights stay)") + ". "
        f"{result['decision'][0].upper() + result['decision'][1:]}.", ""])


def ship(model: str, result: dict, mix: int = 0, where: str = "replace", state: Path | None = None) -> Path:
    """Carry out :func:`decide`'s ``where`` (written beside ``checkpoints/<model>``, then swapped in): ``replace``:
    the run's final weights replace the checkpoint's own, its card the shipped one's with the 256-px stage added
    (steps and CPU seconds summed); ``sizes``: they go to ``sizes/256/`` (with the stage on the card under
    ``sizes``). Both add the stage's command and validation rows to MODEL_CARD.md."""
    import shutil

    dest = ROOT / "checkpoints" / model
    final = state or final_state(model, mix)  # the weights and render options to ship (default: the run's)
    meta = json.loads((final / "meta.json").read_text())
    card = json.loads((dest / "card.json").read_text())
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(dest, tmp)
    full_where, where = where, where.split(":")[0]
    weights = tmp if where == "replace" else tmp / "sizes" / str(SIZE)
    weights.mkdir(parents=True, exist_ok=True)
    shutil.copy2(final / "meta.json", weights / "meta.json")
    if where == "replace":
        shutil.copy2(final / "model.safetensors", weights / "model.safetensors")
    else:  # only the tensors the run changed (a frozen encoder stays in the own weights): checkpoint_weights
        from safetensors.torch import save_file

        from omnirecon.engine.checkpoint import checkpoint_weights, size_delta

        save_file(size_delta(checkpoint_weights(dest), checkpoint_weights(final)), str(weights / "model.safetensors"))
        (weights / "model.safetensors").chmod(0o644)  # readable as the own weights are, in a checkout and a wheel
    stage = _card_stage(meta, card, result, mix, own=full_where.startswith(f"sizes:shipped {model}"))
    text = _card_text(stage, meta, card, result, mix, full_where)
    if where == "replace":
        card = {**card, "steps": card["steps"] + meta["step"], "cpu_seconds": card["cpu_seconds"] + stage["cpu_seconds"],
                "wall_seconds": card["wall_seconds"] + stage["wall_seconds"],
                "cpu_budget_s": card["cpu_budget_s"] + result["cpu_budget"], "stages": [*card["stages"], result["command"]],
                "continued": stage, "provenance": meta.get("provenance", card.get("provenance", {}))}
    else:
        card = {**card, "sizes": {**card.get("sizes", {}), str(SIZE): stage}}
    (tmp / "card.json").write_text(json.dumps(card, indent=1))
    (tmp / "MODEL_CARD.md").write_text((tmp / "MODEL_CARD.md").read_text().rstrip() + "\n\n" + text)
    shutil.rmtree(dest)
    tmp.rename(dest)
    return dest


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="ibrnet-tiny")
    p.add_argument("--train", action="store_true", help="run (or resume) the warm start, then score")
    p.add_argument("--cpu-budget", type=float, default=3600.0, help="process CPU-seconds of the warm start")
    p.add_argument("--steps", type=int, default=950, help="length of the learning-rate schedule")
    p.add_argument("--synth-scenes", type=int, default=4, help="procedural training scenes per rig")
    p.add_argument("--mix", type=int, default=0, help="read half the scenes at this size (px) instead; 0: none")
    p.add_argument("--ship", action="store_true", help="replace checkpoints/<model> by the run where the rule says so")
    p.add_argument("--full-render", action="store_true", help="also score both states at 256 px with every render "
                   "option at its full-render value (the trained sample counts), candidates for the 256-px weights")
    p.add_argument("--samples", type=int, nargs="*", default=[], help="also score both states at 256 px with this "
                   "many samples per ray, the other render options as shipped (models with render_samples), "
                   "candidates for the 256-px weights as the --full-render rows")
    p.add_argument("--out", type=Path, default=None, help="default: bench/results/train_256.json for ibrnet-tiny, "
                   "train_256_<model>.json for the others (--mix R: train_256_mix<R>.json, train_256_mix<R>_<model>.json)")
    a = p.parse_args(argv)
    own = "" if a.model == "ibrnet-tiny" else f"_{a.model}"  # ibrnet-tiny's file kept its first name
    a.out = a.out or Path(__file__).parent / "results" / (f"train_256_mix{a.mix}{own}.json" if a.mix else f"train_256{own}.json")
    from omnirecon.data.io import write_json
    from omnirecon.provenance import provenance

    cmd = train_cmd(a.model, a.cpu_budget, a.steps, a.synth_scenes, a.mix)
    if a.train:
        subprocess.run(cmd, check=True)
    final = final_state(a.model, a.mix)
    meta = json.loads((final / "meta.json").read_text())
    work = ROOT / "outputs" / "train" / "val256"
    shipped_meta = json.loads((ROOT / "checkpoints" / a.model / "meta.json").read_text())
    shipped = {"name": f"shipped {a.model}", "step": shipped_meta["step"],
               **{s: score(own_weights(a.model), work / f"shipped_{a.model}_{s}", s) for s in SETS}}
    run = {"name": f"{a.model} + {meta['step']} steps at {SIZE} px" + (f", half the scenes at {a.mix} px" if a.mix else ""),
           "step": shipped_meta["step"] + meta["step"],
           "cpu_s": round(meta["extra"]["cpu_s"], 1), "checkpoint": str(final.relative_to(ROOT)),
           **{s: score(final, work / f"{run_dir(a.model, a.mix).name}_step{meta['step']}_render_{s}", s) for s in SETS}}
    states = {}
    if a.full_render:  # the same two states at 256 px with the render options at their full-render values
        states = {f"shipped {a.model}, full render": full_render(own_weights(a.model), work.parent / "init" / f"{a.model}_own_full"),
                  f"{run['name']}, full render": full_render(run_dir(a.model, a.mix) / "checkpoints" / "final",
                                                             run_dir(a.model, a.mix) / "final_full")}
    for n in a.samples:  # the same two states with n samples per ray, the other render options as shipped
        states[f"shipped {a.model}, {n} samples"] = with_render(own_weights(a.model), work.parent / "init" / f"{a.model}_own_s{n}",
                                                                samples_render(a.model, n))
        states[f"{run['name']}, {n} samples"] = with_render(run_dir(a.model, a.mix) / "checkpoints" / "final",
                                                            run_dir(a.model, a.mix) / f"final_s{n}", samples_render(a.model, n))
    full = [{"name": name, "step": (shipped if name.startswith("shipped") else run)["step"],
             "checkpoint": str(folder.relative_to(ROOT)), "render": "full" if name.endswith("full render") else "samples",
             "256": score(folder, work / f"{folder.parent.name}_{folder.name}_256", "256")}
            for name, folder in states.items()]
    where, why = decide(shipped, run, full)
    print(why + ": " + ", ".join(f"{k} {v:+.2f}" for k, v in gains(shipped, run).items()))
    result = {"provenance": provenance(seed=SEED), "model": a.model, "size": SIZE, "mix": a.mix, "margin_db": MARGIN_DB,
              "command": " ".join(["nice", "-n", "19", "python", "-m", *cmd[2:]]).replace(str(ROOT) + "/", "")
              .replace(str(SHARED.parent.parent) + "/", "../").replace(" --resume", ""),
              "cpu_budget": a.cpu_budget, "rows": [shipped, run, *full], "ships": where, "decision": why}
    if where and a.ship:
        state = ROOT / next(r["checkpoint"] for r in full if r["name"] == where[6:]) if where.startswith("sizes:") else None
        print(f"shipped {ship(a.model, result, a.mix, where, state)}")
        result["shipped"] = True
    write_json(a.out, result)
    return result


if __name__ == "__main__":
    main()
