"""The fast paths of ``omnirecon/models/fast.py`` against their reference twins on a held-out scene.

    python -m bench fast_paths                      # shipped tiny checkpoints, synth:eval seed 900000
    python -m bench fast_paths --models ibrnet-tiny --targets 1 --rounds 1
    python -m bench fast_paths --compile            # also: torch.compile of IBRNet's aggregator (slow)

For each model (a shipped checkpoint, else random weights: the JSON says which), one held-out procedural
scene (``synth:eval``, first seed, the ``cpu`` protocol: 64 px; ``--protocol-set full``: 128 px) with K = 3 nearest pool views per
target, and each variant:

* ``reference``: every switch at its reference twin (fp32 eager, no_grad, one ``render_rays`` per chunk);
* ``default``: the defaults of ``FastPaths`` (what every command now runs);
* ``bf16``: the defaults plus bf16 autocast of the per-sample networks;
* ``without_sdpa_elu`` (IBRNet): the defaults with ``sdpa_attention`` and ``inplace_elu`` off;
* ``surface_N``: the defaults, rendered with ``surface_samples = N`` (the fine pass on N importance
  samples around the coarse surface only; IBRNet and Omni-Recon; an option of ``render_view``);
* ``coarse_only``: the defaults, rendered with ``fine_pass = False`` (no fine pass: depth maps for meshing).

Reported per variant: render CPU seconds (encode + ``render_view`` of every target; the variants run
interleaved ``--rounds`` times, the fastest round kept: the cores are shared), the speed-up over the
reference *measured in the same run*, PSNR against the ground truth, PSNR against the reference render,
the largest colour difference from the reference, and depth abs-rel (``|d - d_gt| / d_gt`` on pixels
with ground-truth depth that the model marks valid) against the ground truth and against the reference;
``coarse_depth_absrel_gt`` scores the coarse pass's depth (what a depth map without the fine pass gets).
One thread. Writes ``bench/results/fast_paths.json`` with a provenance header.
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
SURFACE = (8, 16, 32)


def variants(model_name: str) -> dict[str, dict]:
    from omnirecon.models.fast import REFERENCE

    out = {"reference": dict(REFERENCE), "default": {}, "bf16": {"bf16_render": True}}
    if model_name.startswith("ibrnet"):  # the defaults without this session's exact levers (SDPA, in-place ELU)
        out["without_sdpa_elu"] = {"sdpa_attention": False, "inplace_elu": False}
    if not model_name.startswith("gpnr"):
        out.update({f"surface_{n}": {"surface_samples": n} for n in SURFACE})
        out["coarse_only"] = {"fine_pass": False}
    return out


def load(model_name: str):
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.models.registry import build_model, full_render

    ckpt = ROOT / "checkpoints" / model_name
    if ckpt.is_dir():
        model, meta = load_checkpoint(ckpt)
        full_render(model)  # the full render (the checkpoint's render options are not what this compares)
        return model.eval(), f"checkpoints/{model_name} step {meta['step']}"
    torch.manual_seed(0)
    return build_model(model_name).eval(), "random weights (no shipped checkpoint)"


def jobs(k: int, targets: int, protocol_set: str = "cpu"):
    """(scene, [(target index, source indices)]) of the first held-out procedural scene."""
    from omnirecon.engine.protocols import targets_and_pool
    from omnirecon.engine.scenes import prepare_scenes
    from omnirecon.engine.views import select_sources

    es = prepare_scenes(["synth:eval"], count=1, cache=ROOT / "outputs" / "cache", protocol_set=protocol_set)[0]
    tgts, pool = targets_and_pool(es.protocol, es.scene)
    tgts = tgts[:targets]
    return es, [(t, select_sources(es.scene, es.scene.cameras[t], pool, k)) for t in tgts]


OPTIONS = ("fine_pass", "surface_samples")
"""Keys of a variant that are options of ``render_view`` (they change the output), not fast-path switches."""


def render_all(model, es, plan, **options) -> tuple[float, list[dict]]:
    from omnirecon.rays import Sources

    scene = es.scene
    outs = []
    t0 = time.process_time()  # CPU seconds of this one-thread process: the shared cores' load does not count
    for t, src in plan:
        sources = Sources.from_scene(scene, src)
        with torch.no_grad():
            feats = model.encode(sources)
        full = {"fine_pass": True} if model.capabilities.passes else {}  # the full render, not the checkpoint's default
        out = model.render_view(feats, scene.cameras[[t]], chunk=4096, **(full | options))
        outs.append({k: v for k, v in out.items() if k in ("rgb", "depth", "depth_coarse", "valid")})
    return time.process_time() - t0, outs


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10 * torch.log10((a.float() - b.float()).square().mean().clamp_min(1e-12)))


def abs_rel(d: torch.Tensor, ref: torch.Tensor, ok: torch.Tensor) -> float | None:
    ok = ok & (ref > 0)
    if not ok.any():
        return None
    return float(((d[ok] - ref[ok]).abs() / ref[ok]).mean())


def measure(model_name: str, k: int, targets: int, rounds: int, protocol_set: str = "cpu") -> dict:
    from omnirecon.models import fast

    model, weights = load(model_name)
    es, plan = jobs(k, targets, protocol_set)
    scene = es.scene
    var = variants(model_name)
    times: dict[str, list[float]] = {v: [] for v in var}
    outs: dict[str, list[dict]] = {}
    with fast.switches(**var["reference"]):  # warm-up
        render_all(model, es, plan[:1])
    for _ in range(rounds):
        for name, sw in var.items():
            with fast.switches(**{k: v for k, v in sw.items() if k not in OPTIONS}):
                t, o = render_all(model, es, plan, **{k: v for k, v in sw.items() if k in OPTIONS})
            times[name].append(t)
            outs[name] = o
    ref = outs["reference"]
    rows = []
    for name in var:
        o = outs[name]
        row = {"variant": name, "switches": var[name], "seconds": round(min(times[name]), 3),
               "seconds_all": [round(x, 3) for x in times[name]],
               "speedup": round(min(times["reference"]) / min(times[name]), 2),
               "psnr_gt": round(sum(psnr(x["rgb"], scene.images[t]) for x, (t, _) in zip(o, plan)) / len(plan), 3),
               "psnr_vs_reference": round(sum(psnr(x["rgb"], r["rgb"]) for x, r in zip(o, ref)) / len(plan), 2),
               "max_abs_vs_reference": round(max(float((x["rgb"] - r["rgb"]).abs().max()) for x, r in zip(o, ref)), 6)}
        if "depth" in ref[0] and scene.depths is not None:
            gt = [abs_rel(x["depth"], scene.depths[t], x.get("valid", torch.ones_like(x["depth"], dtype=torch.bool)))
                  for x, (t, _) in zip(o, plan)]
            vs = [abs_rel(x["depth"], r["depth"], r.get("valid", torch.ones_like(r["depth"], dtype=torch.bool)))
                  for x, r in zip(o, ref)]
            row["depth_absrel_gt"] = round(sum(g for g in gt if g is not None) / max(1, sum(g is not None for g in gt)), 5)
            row["depth_absrel_vs_reference"] = round(sum(v for v in vs if v is not None) / max(1, len(vs)), 6)
            if "depth_coarse" in ref[0]:  # what a depth map from the coarse pass alone would score
                cg = [abs_rel(x["depth_coarse"], scene.depths[t], x.get("valid", torch.ones_like(x["depth"],
                                                                                                  dtype=torch.bool)))
                      for x, (t, _) in zip(o, plan)]
                row["coarse_depth_absrel_gt"] = round(sum(g for g in cg if g is not None)
                                                      / max(1, sum(g is not None for g in cg)), 5)
        rows.append(row)
        print(model_name, row, flush=True)
    return {"model": model_name, "weights": weights, "scene": es.name, "k": k,
            "targets": [t for t, _ in plan], "resolution": [scene.width, scene.height], "rows": rows}


def measure_compile(preset: str = "ibrnet-tiny", rays: int = 256, repeats: int = 5) -> dict:
    """Compile time and steady speed of ``torch.compile`` on IBRNet's fine aggregator (inference, one batch
    shape) against eager, the same inputs, interleaved repeats."""
    from bench.profile_models import setup
    from omnirecon.rays import Rays

    model, src, target, _, _ = setup(preset)
    model.eval()
    with torch.inference_mode():
        feats = model.encode(src)
        S = model.cfg.coarse_samples + model.cfg.fine_samples
        z = torch.linspace(2.0, 4.0, S).expand(rays, S).contiguous()
        inputs = model._gather(feats, Rays.from_image(target)[:rays], z, 1)[:3]
        net = model.fine
        t0 = time.perf_counter()
        compiled = torch.compile(net, dynamic=False)
        compiled(*inputs)
        compile_s = time.perf_counter() - t0
        eager_out, comp_out = net(*inputs), compiled(*inputs)
        te, tc = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            net(*inputs)
            te.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            compiled(*inputs)
            tc.append(time.perf_counter() - t0)
    return {"preset": preset, "module": "fine aggregator", "rays": rays, "samples": S, "compile_s": round(compile_s, 1),
            "eager_ms": round(1000 * min(te), 2), "compiled_ms": round(1000 * min(tc), 2),
            "speedup": round(min(te) / min(tc), 2),
            "max_abs_diff_sigma": float((eager_out[0] - comp_out[0]).abs().max()),
            "max_abs_diff_blend": float((eager_out[1] - comp_out[1]).abs().max())}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS))
    parser.add_argument("--k", type=int, default=3, help="source views")
    parser.add_argument("--targets", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--protocol-set", default="cpu", choices=["cpu", "full"],
                        help="the scene's protocol: cpu (64 px) or full (128 px)")
    parser.add_argument("--compile", action="store_true", help="also time torch.compile of IBRNet's aggregator")
    parser.add_argument("--compile-only", action="store_true",
                        help="only the torch.compile timing, added to an existing --out")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "fast_paths.json")
    args = parser.parse_args(argv)
    from omnirecon.data.io import write_json
    from omnirecon.models.fast import FAST
    from omnirecon.provenance import provenance

    torch.set_num_threads(1)
    if args.compile_only:
        import json

        result = json.loads(args.out.read_text())
        result["compile"] = measure_compile() | {"provenance": provenance(seed=0, threads=1)}
        print(result["compile"])
        write_json(args.out, result)
        return result
    result = {"provenance": provenance(seed=0, threads=1), "defaults": repr(FAST),
              "protocol_set": args.protocol_set,
              "models": [measure(m, args.k, args.targets, args.rounds, args.protocol_set) for m in args.models]}
    if args.compile:
        result["compile"] = measure_compile()
        print(result["compile"])
    result["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    write_json(args.out, result)
    return result

