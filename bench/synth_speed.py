"""Speed of ``omnirecon synth``: scenes x views at a resolution, all-inclusive (layout, rendering, PNG/JSON/PLY).

    python -m bench synth_speed                      # the target: 200 scenes x 40 views at 128^2
    python -m bench synth_speed --scenes 8 --views 40 --workers 2

Prints the wall time, milliseconds per view and scenes per minute, and writes them with a
provenance header (commit, versions, CPU, seed) to ``--out`` as JSON.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

from omnirecon.data.io import write_json
from omnirecon.data.synth.batch import SynthConfig, run_batch
from omnirecon.provenance import provenance

TARGET_SECONDS = 600.0
"""Budget for 200 scenes x 40 views at 128^2 on two cores."""


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=200)
    parser.add_argument("--views", type=int, default=40)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--workers", type=int, default=None, help="default: all CPU cores")
    parser.add_argument("--rig", default="object", choices=["object", "frontal", "forward"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "synth_speed.json")
    parser.add_argument("--keep", type=Path, default=None, help="write the scenes here and keep them")
    args = parser.parse_args(argv)

    folder = args.keep or Path(tempfile.mkdtemp(prefix="synth_speed_"))
    try:
        cfg = SynthConfig(out=folder, num_scenes=args.scenes, seed=args.seed, views=args.views,
                          resolution=args.resolution, rig=args.rig, workers=args.workers, overwrite=True)
        cfg.check()
        timing = run_batch(cfg, quiet=not sys.stdout.isatty())
        size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
    finally:
        if args.keep is None:
            shutil.rmtree(folder, ignore_errors=True)
    views = timing["views"]
    result = {
        "provenance": provenance(seed=args.seed),
        "config": {"scenes": args.scenes, "views": args.views, "resolution": args.resolution, "rig": args.rig,
                   "workers": timing["workers"], "torch_threads_per_worker": 1, "antialias": cfg.antialias,
                   "detail": cfg.detail},
        "seconds": round(timing["seconds"], 2),
        "ms_per_view": round(1000 * timing["seconds"] / views, 2),
        "ms_per_view_per_worker": round(1000 * timing["seconds"] * timing["workers"] / views, 2),
        "scenes_per_minute": round(60 * args.scenes / timing["seconds"], 2),
        "projected_seconds_200x40": round(timing["seconds"] / views * 200 * 40, 1),
        "target_seconds_200x40": TARGET_SECONDS,
        "megabytes_written": round(size / 2**20, 1),
    }
    result["meets_target"] = result["projected_seconds_200x40"] <= TARGET_SECONDS
    result["provenance"]["loadavg_1min_end"] = round(os.getloadavg()[0], 2)
    write_json(args.out, result)
    print(f"{args.scenes} scenes x {args.views} views at {args.resolution}^2 ({args.rig}, {timing['workers']} "
          f"workers): {result['seconds']:.1f} s, {result['ms_per_view']:.1f} ms/view, "
          f"{result['scenes_per_minute']:.1f} scenes/min, {result['megabytes_written']} MB; "
          f"200x40 projected {result['projected_seconds_200x40']:.0f} s (target {TARGET_SECONDS:.0f} s) -> {args.out}")
    return result

