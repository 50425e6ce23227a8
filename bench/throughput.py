"""Training and rendering throughput (rays/s) of each model preset on this machine.

    python bench/throughput.py                  # tiny presets + floor at 64x64, paper presets on a few rays
    python bench/throughput.py --quick          # fewer repeats (tests)

A training step is what ``omnirecon train`` does per step: encode the K source views, render the
batch of target rays, MSE loss, backward, AdamW step. Rendering is ``render_view`` of a full
image under ``no_grad`` with the source features encoded once. Median of the timed repeats after a
warm-up; CUDA is synchronised when used. Writes ``bench/results/throughput.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from omnirecon.cameras import Cameras, look_at
from omnirecon.data.io import write_json
from omnirecon.models.registry import build_model
from omnirecon.provenance import provenance
from omnirecon.rays import Rays, Sources

# (preset, rays per training step, image side for rendering, rays rendered for paper presets)
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
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        sync(device)
        t = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def measure(preset: str, rays_per_step: int, side: int, render_rays: int | None, repeats: int, device: str) -> dict:
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
            out = model.render_rays(model.encode(src), batch)
            loss = out["rgb"].square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

        t = timed(step, repeats, device)
        row.update(train_step_s=round(t, 4), train_rays_per_s=round(rays_per_step / t, 1))
    model.eval()
    with torch.no_grad():
        feats = model.encode(src)
        if render_rays is None:  # a whole image
            t = timed(lambda: model.render_view(feats, target, chunk=4096), max(1, repeats // 2), device)
            n = side * side
        else:  # paper presets are too slow for a full image on a CPU: time a batch of rays
            t = timed(lambda: model.render_rays(feats, all_rays[:render_rays]), max(1, repeats // 2), device)
            n = render_rays
    row.update(render_rays=n, render_s=round(t, 4), render_rays_per_s=round(n / t, 1),
               render_fps_at_resolution=round(n / t / (side * side), 4))
    return row


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 repeat, tiny presets at 16x16 (tests)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
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
    rows = list(kept)
    for preset, rays, side, render_rays in cases:
        rows.append(measure(preset, rays, side, render_rays, repeats, args.device))
        print(rows[-1])
    order = [c[0] for c in CASES]
    rows.sort(key=lambda r: order.index(r["preset"]) if r["preset"] in order else len(order))
    result = {"provenance": provenance(seed=0), "device": args.device, "repeats": repeats, "rows": rows}
    write_json(args.out, result)
    return result


if __name__ == "__main__":
    main()
