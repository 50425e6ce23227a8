"""Render levers of the tiny presets against their reference twins, over several held-out scenes, in one run.

    python -m bench tiny_levers                                   # every preset, its candidate levers
    python -m bench tiny_levers --models ibrnet-tiny --scenes synth:eval ../shared/data/llff/fern --rounds 1
    python -m bench tiny_levers --candidates coarse_only bf16 bf16_samples_24 --targets 2   # the chosen levers only

The issue's goal is a render throughput of 3x what the tiny presets had before the fast paths (their
reference twins: fp32 eager, every switch off) *at equal quality*. For each shipped tiny checkpoint and
each candidate, on every scene (``synth:eval`` seeds under the ``cpu`` protocol set, plus real scenes given
by path; K = 3 nearest pool views per target, ``--targets`` targets per scene):

* ``reference``: every fast-path switch at its reference twin (the throughput before the fast paths);
* ``default``: the defaults of ``FastPaths``, the full render (both passes, every sample, fp32);
* ``checkpoint``: what every command now runs: the defaults with the checkpoint's own render options
  (``model_config``: gpnr-tiny's ``render_samples`` / ``render_bf16``, omnirecon-tiny's ``render_fine_pass``);
* switches (``bf16``: bf16 autocast of the per-sample networks), render options (``coarse_only``:
  ``fine_pass=False``; ``surface_N``: the fine pass on N importance samples only) and sample counts
  (``fine_N`` / ``coarse_N`` / ``samples_N``: the model's config changed at render time, no retraining).

Reported per candidate: render CPU seconds over every target (encode + ``render_view``, one thread; the
candidates run interleaved ``--rounds`` times, each one's fastest round kept), the speed-up over the
reference measured in the same run, mean PSNR against the ground truth per scene and over all scenes, and
its difference from the reference render's PSNR (``dpsnr``: the quality cost). Writes
``bench/results/tiny_levers.json`` with a provenance header and the load average at start and end.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
MODELS = ("ibrnet-tiny", "omnirecon-tiny", "gpnr-tiny")
OPTIONS = ("fine_pass", "surface_samples")
"""Keys of a candidate that are options of ``render_view`` (they change the output)."""
CONFIG = ("coarse_samples", "fine_samples", "num_samples", "render_coarse_samples", "render_fine_samples")
"""Keys of a candidate that change the model's config at render time (sample counts)."""


def candidates(model_name: str) -> dict[str, dict]:
    from omnirecon.models.fast import REFERENCE

    out = {"reference": dict(REFERENCE), "default": {}, "checkpoint": {}, "bf16": {"bf16_render": True}}
    if model_name.startswith("gpnr"):
        out.update({"samples_24": {"num_samples": 24}, "samples_16": {"num_samples": 16},
                    "bf16_samples_24": {"bf16_render": True, "num_samples": 24}})
    else:
        out.update({"coarse_only": {"fine_pass": False}, "bf16_coarse_only": {"bf16_render": True, "fine_pass": False},
                    "fine_8": {"fine_samples": 8}, "coarse_16": {"coarse_samples": 16},
                    "coarse_24_fine_8": {"coarse_samples": 24, "fine_samples": 8},
                    "coarse_24": {"coarse_samples": 24}, "coarse_20_fine_12": {"coarse_samples": 20, "fine_samples": 12},
                    "coarse_16_fine_8": {"coarse_samples": 16, "fine_samples": 8},
                    "bf16_coarse_16": {"bf16_render": True, "coarse_samples": 16},
                    "batch_128": {"render_batch": 128}, "batch_512": {"render_batch": 512},
                    "surface_16": {"surface_samples": 16}})
    if model_name.startswith("ibrnet"):  # fewer samples standing for the trained ones (index code, density rescaled)
        out.update({f"render_{c}_{f}": {"render_coarse_samples": c, "render_fine_samples": f}
                    for c, f in ((16, 16), (16, 12), (16, 8), (20, 10), (24, 8), (12, 8))})
        out["bf16_render_16_8"] = {"bf16_render": True, "render_coarse_samples": 16, "render_fine_samples": 8}
    return out


def load(model_name: str):
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.models.registry import full_render

    model, meta = load_checkpoint(ROOT / "checkpoints" / model_name)
    own = model.cfg
    full_render(model)  # the full render; the checkpoint's own render options are the candidate "checkpoint"
    return model.eval(), f"checkpoints/{model_name} step {meta['step']}", own


def jobs(specs: list[str], count: int, k: int, targets: int):
    """[(eval scene, [(target, sources)])] for every scene of ``specs`` (cpu protocol set)."""
    from omnirecon.engine.protocols import targets_and_pool
    from omnirecon.engine.scenes import prepare_scenes
    from omnirecon.engine.views import select_sources

    out = []
    for es in prepare_scenes(specs, count=count, cache=ROOT / "outputs" / "cache", protocol_set="cpu"):
        tgts, pool = targets_and_pool(es.protocol, es.scene)
        out.append((es, [(t, select_sources(es.scene, es.scene.cameras[t], pool, k)) for t in tgts[:targets]]))
    return out


def render_all(model, plans, **options) -> tuple[float, list[list[torch.Tensor]]]:
    from omnirecon.rays import Sources

    outs = []
    t0 = time.process_time()  # CPU seconds of this one-thread process: the shared cores' load does not count
    for es, plan in plans:
        per = []
        for t, src in plan:
            sources = Sources.from_scene(es.scene, src)
            with torch.no_grad():
                feats = model.encode(sources)
            per.append(model.render_view(feats, es.scene.cameras[[t]], chunk=4096, **options)["rgb"])
        outs.append(per)
    return time.process_time() - t0, outs


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10 * torch.log10((a.float() - b.float()).square().mean().clamp_min(1e-12)))


def measure(model_name: str, plans, rounds: int, only: list[str] | None = None) -> dict:
    from omnirecon.models import fast

    model, weights, own = load(model_name)
    full = model.cfg
    base_cfg = {k: getattr(model.cfg, k) for k in CONFIG if hasattr(model.cfg, k)}
    cands = {k: v for k, v in candidates(model_name).items()
             if not only or k in ("reference", "default", "checkpoint", *only)}
    times: dict[str, list[float]] = {c: [] for c in cands}
    outs: dict[str, list] = {}
    with fast.switches(**cands["reference"]):  # warm-up
        render_all(model, plans[:1])
    for _ in range(rounds):
        for name, spec in cands.items():
            model.cfg = own if name == "checkpoint" else full
            for key, value in base_cfg.items():  # the checkpoint's own config keeps its render options
                if name != "checkpoint" or key in spec:
                    setattr(model.cfg, key, spec.get(key, value))
            options = {"fine_pass": True} if model.capabilities.passes and name != "checkpoint" else {}
            options |= {k: v for k, v in spec.items() if k in OPTIONS}  # the full render unless a lever says otherwise
            with fast.switches(**{k: v for k, v in spec.items() if k not in OPTIONS + CONFIG}):
                t, o = render_all(model, plans, **options)
            times[name].append(t)
            outs[name] = o
    for key, value in base_cfg.items():
        setattr(model.cfg, key, value)
    rows = []
    for name, spec in cands.items():
        per_scene = {es.name: round(sum(psnr(x, es.scene.images[t]) for x, (t, _) in zip(o, plan)) / len(plan), 3)
                     for (es, plan), o in zip(plans, outs[name])}
        rows.append({"candidate": name, "spec": spec, "cpu_s": round(min(times[name]), 3),
                     "cpu_s_all": [round(x, 3) for x in times[name]],
                     "speedup": round(min(times["reference"]) / min(times[name]), 2),
                     "psnr": per_scene, "psnr_mean": round(sum(per_scene.values()) / len(per_scene), 3)})
    ref = rows[0]["psnr_mean"]
    for r in rows:
        r["dpsnr"] = round(r["psnr_mean"] - ref, 3)
        print(model_name, r, flush=True)
    return {"model": model_name, "weights": weights, "config": base_cfg, "rows": rows}


def switch_ablation(preset: str, rounds: int) -> dict:
    """Each fast-path switch measured against its reference twin: render CPU seconds of ``preset`` (random
    weights, ``bench/profile_models.py``'s case: sources and a small target) with every switch at its reference
    but that one (``only_<switch>``), with the defaults but that one at its reference (``without_<switch>``),
    and both ends; interleaved ``rounds`` times, fastest kept, one thread."""
    from bench.profile_models import setup
    from omnirecon.models import fast

    model, src, target, _, _ = setup(preset)
    model.eval()
    ref = dict(fast.REFERENCE)
    default = {k: getattr(fast.FastPaths(), k) for k in ref}
    on = [k for k in ref if default[k] != ref[k]]
    sides = {"reference": ref, "default": default}
    sides |= {f"only_{k}": ref | {k: default[k]} for k in on}
    sides |= {f"without_{k}": default | {k: ref[k]} for k in on}
    times: dict[str, list[float]] = {n: [] for n in sides}
    rgb: dict[str, torch.Tensor] = {}

    def render():
        t0 = time.process_time()
        with torch.no_grad():
            feats = model.encode(src)
        out = model.render_view(feats, target, chunk=4096)["rgb"]
        return time.process_time() - t0, out

    with fast.switches(**ref):
        render()  # warm-up
    for _ in range(rounds):
        for name, sw in sides.items():
            with fast.switches(**sw):
                t, rgb[name] = render()
            times[name].append(t)
    base = min(times["reference"])
    rows = [{"side": n, "cpu_s": round(min(t), 3), "speedup": round(base / min(t), 2),
             "max_abs_vs_reference": float((rgb[n] - rgb["reference"]).abs().max())} for n, t in times.items()]
    for row in rows:
        print(preset, row, flush=True)
    return {"preset": preset, "target": [target.width, target.height], "sources": len(src.cameras), "rows": rows}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS))
    parser.add_argument("--scenes", nargs="+", default=["synth:eval", "../shared/data/llff/fern",
                                                        "../shared/data/neus_dtu/dtu_scan24"])
    parser.add_argument("--count", type=int, default=2, help="synth:eval seeds")
    parser.add_argument("--k", type=int, default=3, help="source views")
    parser.add_argument("--targets", type=int, default=1, help="targets per scene")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--candidates", nargs="*", default=None, metavar="NAME",
                        help="only these candidates (besides reference and default), e.g. coarse_only bf16_samples_24")
    parser.add_argument("--switches", nargs="*", default=None, metavar="PRESET",
                        help="instead: each fast-path switch against its reference twin on these presets (random "
                             "weights, bench/profile_models.py's cases); writes --out (default switches.json)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    from omnirecon.data.io import write_json
    from omnirecon.models.fast import FAST
    from omnirecon.provenance import provenance

    torch.set_num_threads(1)
    load_start = [round(x, 2) for x in os.getloadavg()]
    if args.switches is not None:
        result = {"provenance": provenance(seed=0, threads=1), "defaults": repr(FAST), "rounds": args.rounds,
                  "loadavg_start": load_start,
                  "presets": [switch_ablation(p, args.rounds) for p in args.switches or ["ibrnet-paper", "ibrnet-tiny"]],
                  "loadavg_end": [round(x, 2) for x in os.getloadavg()]}
        write_json(args.out or HERE / "results" / "switches.json", result)
        return result
    plans = jobs(args.scenes, args.count, args.k, args.targets)
    result = {"provenance": provenance(seed=0, threads=1), "defaults": repr(FAST), "protocol_set": "cpu",
              "k": args.k, "targets_per_scene": args.targets, "rounds": args.rounds,
              "scenes": [{"name": es.name, "size": [es.scene.width, es.scene.height], "targets": [t for t, _ in p]}
                         for es, p in plans], "loadavg_start": load_start,
              "models": [measure(m, plans, args.rounds, args.candidates) for m in args.models]}
    result["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    write_json(args.out or HERE / "results" / "tiny_levers.json", result)
    return result
