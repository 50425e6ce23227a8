"""Training and rendering throughput (rays/s) of each model preset on this machine.

    python -m bench throughput                  # tiny presets + floor at 64x64, paper presets on a few rays
    python -m bench throughput --quick          # fewer repeats (tests)

A training step is what ``omnirecon train`` does per step: encode the K source views, render the
batch of target rays, MSE loss, backward, AdamW step. Rendering is ``render_view`` of a full
image with the source features encoded once. Median of the timed repeats after a warm-up; CUDA is
synchronised when used. ``--threads`` torch threads (default 1: the cores are shared).

Before/after in the same run: every preset is timed with the fast paths of
``omnirecon/models/fast.py`` at their reference twins (``reference``: fp32 eager, the code before the
fast paths) and at their defaults (the row's main numbers), the two interleaved repeat by repeat so
that both see the same machine load; ``speedup_*`` is their ratio. Writes
``bench/results/throughput.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from contextlib import nullcontext
from pathlib import Path

import torch

from omnirecon.cameras import Cameras, look_at
from omnirecon.data.io import write_json
from omnirecon.models.registry import build_model
from omnirecon.provenance import provenance
from omnirecon.rays import Rays, Sources

# (preset, rays per training step, image side for rendering, pixels of the small view rendered for paper presets)
CASES = [("floor", 4096, 64, None), ("gpnr-tiny", 256, 64, None), ("ibrnet-tiny", 512, 64, None),
         ("omnirecon-tiny", 256, 64, None), ("gpnr-paper", 4, 64, 16), ("ibrnet-paper", 32, 64, 256),
         ("omnirecon-paper", 32, 64, 256)]
"""Paper presets cost ~16 GFLOP (GPNR) per ray forward: a CPU times them on a handful of rays."""


def rig(k: int, side: int, device) -> Cameras:
    ang = torch.linspace(-0.5, 0.5, k + 1)
    eye = torch.stack([3 * torch.sin(ang), -3 * torch.cos(ang), 0.5 + 0 * ang], -1)
    c2w = look_at(eye, torch.zeros(3), torch.tensor([0, 0, 1.0]))
    f = torch.full((k + 1,), 1.2 * side)
    return Cameras(f, f, f * 0 + side / 2, f * 0 + side / 2, c2w, side, side).to(device)


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def timed(fn, repeats: int, device: str) -> float:
    return timed_pair(fn, repeats, device)["default"]


def timed_pair(fn, repeats: int, device: str, compare: bool = False) -> dict[str, float]:
    """Median seconds of ``fn`` with the fast paths at their defaults and (``compare``) at their reference
    twins, interleaved repeat by repeat after one warm-up each."""
    from omnirecon.models.fast import reference

    modes = {"default": nullcontext, **({"reference": reference} if compare else {})}
    times: dict[str, list[float]] = {m: [] for m in modes}
    for ctx in modes.values():
        with ctx():
            fn()  # warm-up
    for _ in range(repeats):
        for m, ctx in modes.items():
            with ctx():
                sync(device)
                t = time.perf_counter()
                fn()
                sync(device)
                times[m].append(time.perf_counter() - t)
    return {m: statistics.median(v) for m, v in times.items()}


def measure(preset: str, rays_per_step: int, side: int, render_rays: int | None, repeats: int, device: str,
            compare: bool = True) -> dict:
    torch.manual_seed(0)
    model = build_model(preset).to(device)
    k = getattr(model.cfg, "num_views", 5)
    cams = rig(k, side, device)
    images = torch.rand(k, side, side, 3, device=device)
    src = Sources(images, cams[list(range(k))], 2.0, 4.0, "object")
    target = cams[[k]]
    all_rays = Rays.from_image(target)
    batch = all_rays[torch.randperm(len(all_rays))[:rays_per_step].to(device)]
    params = [p for p in model.parameters() if p.requires_grad]
    row = {"preset": preset, "params": sum(p.numel() for p in params), "source_views": k, "resolution": side,
           "rays_per_step": rays_per_step}
    if params:
        opt = torch.optim.AdamW(params, lr=1e-4)

        def step():
            out = model.render_rays_batched(model.encode(src), batch)  # as the training loss does
            loss = out["rgb"].square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

        tt = timed_pair(step, repeats, device, compare)
        t = tt["default"]
        row.update(train_step_s=round(t, 4), train_rays_per_s=round(rays_per_step / t, 1))
        if compare:
            row["reference"] = {"train_step_s": round(tt["reference"], 4),
                                "train_rays_per_s": round(rays_per_step / tt["reference"], 1)}
            row["speedup_train"] = round(tt["reference"] / t, 2)
    model.eval()
    with torch.no_grad():
        feats = model.encode(src)
    if render_rays is None:  # a whole image
        n = side * side
        tt = timed_pair(lambda: model.render_view(feats, target, chunk=4096), max(1, repeats // 2), device, compare)
    else:  # paper presets are too slow for a full image on a CPU: a small image of render_rays pixels
        small = rig(k, round(render_rays ** 0.5), device)[[k]]  # the same view, fewer pixels
        n = small.width * small.height
        tt = timed_pair(lambda: model.render_view(feats, small, chunk=4096), max(1, repeats // 2), device, compare)
    t = tt["default"]
    row.update(render_rays=n, render_s=round(t, 4), render_rays_per_s=round(n / t, 1),
               render_fps_at_resolution=round(n / t / (side * side), 4))
    if compare:
        row.setdefault("reference", {}).update(render_s=round(tt["reference"], 4),
                                               render_rays_per_s=round(n / tt["reference"], 1))
        row["speedup_render"] = round(tt["reference"] / t, 2)
    return row


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 repeat, tiny presets at 16x16 (tests)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (CPU)")
    parser.add_argument("--no-compare", action="store_true",
                        help="time only the defaults (not also the reference twins)")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "throughput.json")
    parser.add_argument("--presets", nargs="+", default=None,
                        help="measure only these presets and keep the other rows of --out (same device)")
    args = parser.parse_args(argv)
    cases = [(p, min(r, 64), 16, x) for p, r, _, x in CASES[:4]] if args.quick else CASES
    kept = []
    if args.presets:
        cases = [c for c in cases if c[0] in args.presets]
        if args.out.is_file():
            old = json.loads(args.out.read_text())
            if old.get("device") == args.device:
                kept = [dict(r, provenance=old["provenance"]) for r in old["rows"] if r["preset"] not in args.presets]
    repeats = 1 if args.quick else args.repeats
    torch.set_num_threads(args.threads)
    rows = list(kept)
    for preset, rays, side, render_rays in cases:
        rows.append(measure(preset, rays, side, render_rays, repeats, args.device, not args.no_compare))
        print(rows[-1])
    order = [c[0] for c in CASES]
    rows.sort(key=lambda r: order.index(r["preset"]) if r["preset"] in order else len(order))
    result = {"provenance": provenance(seed=0, threads=args.threads), "device": args.device, "repeats": repeats,
              "compared": not args.no_compare, "rows": rows,
              "loadavg_end": [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None}
    write_json(args.out, result)
    return result

