"""Where time and memory go: each model per stage, fp32 eager, one thread, rendering and one training step.

    python -m bench profile_models                       # ibrnet-tiny, gpnr-tiny, omnirecon-tiny, ibrnet-paper
    python -m bench profile_models --presets ibrnet-tiny --repeats 1
    python -m bench profile_models --fast                # the same with the fast paths on (models/fast.py)

Stages are timed with ``perf_counter`` around the models' own methods and sub-modules (wrapped on the
instance for the run, nothing else changes): **encode**; per pass (``coarse``, ``fine``)
**projection + sampling** (projecting the samples into the source views and bilinear sampling of
features and colours; Omni-Recon also samples its feature volume), **aggregation** (the per-sample
networks: IBRNet's MLP, Omni-Recon's geometry and appearance branches, GPNR's token projection),
**ray transformer** (attention along each ray: IBRNet's one layer, Omni-Recon's ray and volume
attention, GPNR's three transformers), **compositing** (what the pass does besides: alpha, weights,
composite, ray geometry), **importance sampling** (fine depths from the coarse weights). Times are
*self* times (a stage's nested stages are not counted twice); ``other`` is the rest of the wall
time (render_view's chunking, loss, ...). A training step adds **backward** and the **optimizer**
step; its forward is timed per stage like rendering.

Memory: the peak resident set size of a fresh process per (preset, mode) (``ru_maxrss``, the
interpreter and torch included: ``baseline_rss_mb`` is the process before the model is built) and
the operators that allocate the most (torch.profiler ``self_cpu_memory_usage``) with the top
operators by self CPU time, backward included.

The scene is a synthetic rig of random images (timing does not depend on the weights or the
content; each model runs the preset's sample counts). Writes ``bench/results/profile.json`` (or
``profile_fast.json`` with ``--fast``) with a provenance header.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from collections import defaultdict
from contextlib import nullcontext
from pathlib import Path

HERE = Path(__file__).resolve().parent

CASES = {
    # preset: (source views, source W, H, target W, H, rays per training step)
    "ibrnet-tiny": (5, 64, 64, 64, 64, 512),
    "gpnr-tiny": (5, 64, 64, 64, 64, 256),
    "omnirecon-tiny": (4, 64, 64, 64, 64, 256),
    "ibrnet-paper": (3, 200, 150, 40, 30, 500),
}
"""``ibrnet-paper`` at the peer benchmark's configuration (3 views of 200x150, 64 + 64 samples, 500 rays
per step), rendering a small 40x30 target; the tiny presets as ``python -m bench throughput`` runs them."""


def maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class StageClock:
    """Self times of nested, labelled calls; labels carry the current pass (``coarse`` / ``fine``)."""

    def __init__(self):
        self.times: dict[str, float] = defaultdict(float)
        self.stack: list[float] = []
        self.pass_ = "coarse"

    def wrap(self, fn, stage: str, per_pass: bool = True):
        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            self.stack.append(0.0)
            try:
                return fn(*args, **kwargs)
            finally:
                dt = time.perf_counter() - t0
                nested = self.stack.pop()
                self.times[f"{self.pass_}/{stage}" if per_pass else stage] += dt - nested
                if self.stack:
                    self.stack[-1] += dt
        return timed

    def patch(self, obj, attr: str, stage: str, per_pass: bool = True) -> None:
        """Time ``obj.attr`` (a method or a module's forward) as ``stage`` on this instance."""
        if attr == "forward":
            obj.forward = self.wrap(obj.forward, stage, per_pass)
        else:
            setattr(obj, attr, self.wrap(getattr(obj, attr), stage, per_pass))


def instrument(model, clock: StageClock) -> list:
    """Wrap the model's stages; returns (module, name, original) triples patched at module level."""
    from omnirecon.models import gpnr, ibrnet, omnirecon

    globals_patched = []
    clock.patch(model, "encode", "encode", per_pass=False)
    if isinstance(model, ibrnet.IBRNet):
        inner_pass = model._pass

        def tagged(net, *a, **k):
            clock.pass_ = "coarse" if net is model.coarse else "fine"
            return inner_pass(net, *a, **k)

        model._pass = clock.wrap(tagged, "compositing")
        clock.patch(model, "_gather", "projection+sampling")
        for net in (model.coarse, model.fine):
            if net is not None:
                clock.patch(net, "forward", "aggregation")
                clock.patch(net.attn, "forward", "ray transformer")
        globals_patched.append((ibrnet, "fine_depths", ibrnet.fine_depths))
        ibrnet.fine_depths = clock.wrap(ibrnet.fine_depths, "importance sampling", per_pass=False)
    elif isinstance(model, omnirecon.OmniRecon):
        inner_pass, calls = model._pass, [0]
        inner_render = model.render_rays

        def render(*a, **k):
            calls[0] = 0
            return inner_render(*a, **k)

        def tagged(*a, **k):
            clock.pass_ = "coarse" if calls[0] == 0 else "fine"
            calls[0] += 1
            return inner_pass(*a, **k)

        model.render_rays = render
        model._pass = clock.wrap(tagged, "compositing")
        clock.patch(model, "gather", "projection+sampling")
        clock.patch(model, "volume_features", "projection+sampling")
        clock.patch(model.geometry, "forward", "aggregation")
        clock.patch(model.appearance, "forward", "aggregation")
        for block in model.geometry.blocks:
            clock.patch(block.ray, "forward", "ray transformer")
            clock.patch(block.cross, "forward", "ray transformer")
        globals_patched.append((omnirecon, "fine_depths", omnirecon.fine_depths))
        omnirecon.fine_depths = clock.wrap(omnirecon.fine_depths, "importance sampling", per_pass=False)
    elif isinstance(model, gpnr.GPNR):
        clock.patch(model, "render_rays", "compositing")
        for name in ("project", "sample"):
            globals_patched.append((gpnr, name, getattr(gpnr, name)))
            setattr(gpnr, name, clock.wrap(getattr(gpnr, name), "projection+sampling"))
        clock.patch(model.key_proj, "forward", "aggregation")
        for block in (model.visual, model.epipolar, model.view):
            clock.patch(block, "forward", "ray transformer")
    return globals_patched


def restore(patched: list) -> None:
    for mod, name, fn in patched:
        setattr(mod, name, fn)


def setup(preset: str, device: str = "cpu"):
    """The model (seed 0), its sources, the target camera, a training batch of rays and target colours."""
    import torch

    from omnirecon.cameras import Cameras, look_at
    from omnirecon.models.registry import build_model
    from omnirecon.rays import Rays, Sources

    k, sw, sh, tw, th, nrays = CASES[preset]
    torch.manual_seed(0)
    model = build_model(preset).to(device)
    ang = torch.linspace(-0.5, 0.5, k + 1)
    eye = torch.stack([3 * torch.sin(ang), -3 * torch.cos(ang), 0.5 + 0 * ang], -1)
    c2w = look_at(eye, torch.zeros(3), torch.tensor([0, 0, 1.0]))

    def cams(idx, w, h):
        f = torch.full((len(idx),), 1.2 * max(w, h))
        return Cameras(f, f, f * 0 + w / 2, f * 0 + h / 2, c2w[idx], w, h).to(device)

    src = Sources(torch.rand(k, sh, sw, 3, device=device), cams(list(range(k)), sw, sh), 2.0, 4.0, "object",
                  torch.tensor([[-1.0] * 3, [1.0] * 3], device=device))
    target = cams([k], tw, th)
    train_cam = cams([k], sw, sh)
    all_rays = Rays.from_image(train_cam)
    g = torch.Generator().manual_seed(0)
    batch = all_rays[torch.randperm(len(all_rays), generator=g)[:nrays].to(device)]
    rgb = torch.rand(nrays, 3, generator=g).to(device)
    return model, src, target, batch, rgb


def run_one(preset: str, mode: str, repeats: int, fast: bool, ops: int) -> dict:
    """Profile ``preset`` in ``mode`` (``render`` or ``train``) in this process."""
    import torch

    from omnirecon.engine.losses import LossModule
    from omnirecon.models import fast as fastpaths

    torch.set_num_threads(1)
    base_rss = maxrss_mb()
    ctx = nullcontext() if fast else fastpaths.reference()
    with ctx:
        model, src, target, batch, rgb = setup(preset)
        clock = StageClock()
        if mode == "render":
            model.eval()

            def work():
                with torch.no_grad():
                    feats = model.encode(src)
                model.render_view(feats, target, chunk=4096)
        else:
            model.train()
            loss_mod = LossModule(model, aux_weight=1.0)
            opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-4)
            loss_mod.backward_ = clock.wrap(lambda loss: loss.backward(), "backward", per_pass=False)
            opt.step = clock.wrap(opt.step, "optimizer", per_pass=False)

            def work():
                torch.manual_seed(1)
                loss, _, _ = loss_mod(src, batch, rgb)
                opt.zero_grad(set_to_none=True)
                loss_mod.backward_(loss)
                opt.step()

        work()  # warm-up (untimed, uninstrumented)
        patched = instrument(model, clock)
        walls = []
        per_stage: list[dict[str, float]] = []
        try:
            for _ in range(repeats):
                clock.times.clear()
                t0 = time.perf_counter()
                work()
                walls.append(time.perf_counter() - t0)
                per_stage.append(dict(clock.times))
        finally:
            restore(patched)
        best = min(range(repeats), key=lambda i: walls[i])  # the least disturbed repeat (shared cores)
        stages = per_stage[best]
        stages["other"] = walls[best] - sum(stages.values())
        peak = maxrss_mb()
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
            work()
        events = prof.key_averages()
        by_time = sorted(events, key=lambda e: e.self_cpu_time_total, reverse=True)[:ops]
        by_mem = sorted(events, key=lambda e: e.self_cpu_memory_usage, reverse=True)[:ops]
        total_us = sum(e.self_cpu_time_total for e in events)
    n_rays = target.width * target.height if mode == "render" else len(batch)
    return {
        "preset": preset, "mode": mode, "fast": fast, "rays": n_rays,
        "wall_s": round(walls[best], 4), "wall_s_all": [round(w, 4) for w in walls],
        "rays_per_s": round(n_rays / walls[best], 1),
        "stages_s": {k: round(v, 4) for k, v in sorted(stages.items(), key=lambda kv: -kv[1])},
        "peak_rss_mb": round(peak, 1), "baseline_rss_mb": round(base_rss, 1),
        "top_ops_time": [{"op": e.key, "self_s": round(e.self_cpu_time_total / 1e6, 4),
                          "share": round(e.self_cpu_time_total / max(total_us, 1), 3), "calls": e.count}
                         for e in by_time],
        "top_ops_memory": [{"op": e.key, "self_alloc_mb": round(e.self_cpu_memory_usage / 2**20, 1), "calls": e.count}
                           for e in by_mem],
    }


def summary(row: dict) -> dict[str, float]:
    """Stage times folded to the issue's stages: encode, projection+sampling, aggregation, ray transformer,
    compositing, fine pass (every stage of the fine pass), backward, optimizer, other."""
    out: dict[str, float] = defaultdict(float)
    for k, v in row["stages_s"].items():
        if k.startswith("fine/"):
            out["fine pass"] += v
        else:
            out[k.split("/")[-1]] += v
    return {k: round(v, 4) for k, v in out.items()}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--modes", nargs="+", default=["render", "train"], choices=["render", "train"])
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (the fastest is kept)")
    parser.add_argument("--fast", action="store_true", help="fast paths on (default: the fp32 eager reference twins)")
    parser.add_argument("--ops", type=int, default=10, help="operators listed by time and by memory")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--child", nargs=2, metavar=("PRESET", "MODE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(run_one(args.child[0], args.child[1], args.repeats, args.fast, args.ops)))
        return {}
    from omnirecon.data.io import write_json
    from omnirecon.provenance import provenance

    out = args.out or HERE / "results" / ("profile_fast.json" if args.fast else "profile.json")
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(HERE.parent), os.environ.get("PYTHONPATH", "")]))
    rows = []
    for preset in args.presets:
        for mode in args.modes:  # a fresh process each: peak RSS is per (preset, mode)
            cmd = [sys.executable, "-m", "bench", "profile_models", "--child", preset, mode, "--repeats", str(args.repeats),
                   "--ops", str(args.ops), *(["--fast"] if args.fast else [])]
            res = subprocess.run(cmd, env=env, capture_output=True, text=True)
            if res.returncode:
                raise SystemExit(f"{preset} {mode} failed:\n{res.stderr[-3000:]}")
            rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
            r = rows[-1]
            print(f"{preset:15s} {mode:6s} {r['wall_s']:8.3f} s  {r['rays_per_s']:9.1f} rays/s  "
                  f"peak {r['peak_rss_mb']:.0f} MB  " + ", ".join(f"{k} {v:.3f}" for k, v in summary(r).items()),
                  flush=True)
    result = {"provenance": provenance(seed=0, threads=1, note="fast paths on" if args.fast else
                                       "fp32 eager reference twins"),
              "cases": {p: dict(zip(("source_views", "source_w", "source_h", "target_w", "target_h", "train_rays"),
                                    CASES[p])) for p in args.presets},
              "repeats": args.repeats, "rows": rows, "stages": {f"{r['preset']}/{r['mode']}": summary(r) for r in rows},
              "loadavg_end": [round(x, 2) for x in os.getloadavg()]}
    write_json(out, result)
    return result

