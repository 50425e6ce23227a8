"""Regenerate BENCHMARKS.md: run the benchmarks (or reuse their stored results) and write the page.

    python -m bench page                 # run every benchmark (hours on 2 CPU cores), then write BENCHMARKS.md
    python -m bench page --skip ablation # all but the GPNR ablation (which retrains four models)
    python -m bench page --only quality geometry   # rerun some (e.g. the ones the page marks stale)
    python -m bench page --reuse         # only rewrite BENCHMARKS.md from bench/results/*.json
    python -m bench page --tiny --out /tmp/B.md --results /tmp/r   # a fast subset (used by the tests)

Every number on the page comes from a JSON file in ``bench/results/`` written by a module of ``bench/``;
each file carries its own provenance header (commit, versions, device, seed, load). The Markdown of each
section is written by ``bench/report/`` from those files only.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from bench.report import write_page
from bench.report.common import GEOMETRY_MODELS, QUALITY_MODELS

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


# Every benchmark behind the page, in the order they run (mesh_path reuses geometry's meshes).
# The first four make up --tiny (the test); "ablation" retrains four GPNR rows (about 1 h of CPU).
STEPS = ("synth", "throughput", "quality", "geometry", "mesh_fps", "mesh_path", "lift", "lift_extra", "geometry_budget",
         "ablation", "poses", "reliability", "fast_paths", "peer_ibrnet", "tiny_levers", "compile_cache",
         "end_to_end")
TINY_STEPS = STEPS[:4]


def run_benchmarks(results: Path, tiny: bool, steps: tuple[str, ...] = STEPS, threads: int = 1) -> None:
    """Run the benchmarks of ``steps``; each writes its JSON into ``results``."""
    from bench import (
        ablation_gpnr,
        compile_cache,
        end_to_end,
        fast_paths,
        geometry,
        geometry_budget,
        lift,
        lift_extra,
        mesh_path,
        peer_ibrnet,
        quality,
        reliability,
        synth_speed,
        throughput,
        tiny_levers,
    )
    from omnirecon.engine.speed import BenchConfig, measure

    results.mkdir(parents=True, exist_ok=True)
    t = ["--tiny"] if tiny else []
    shipped = [m for m in QUALITY_MODELS[1:] if (ROOT / "checkpoints" / m).is_dir()]
    peer_root = os.environ.get("IBRNET_ROOT") or next(
        (str(p) for p in [ROOT.parent / "shared" / "peer" / "IBRNet"] if p.is_dir()), None)
    runs = {
        "synth": lambda: synth_speed.main([*(["--scenes", "2", "--views", "8", "--resolution", "32"] if tiny else []),
                                           "--out", str(results / "synth_speed.json")]),
        "throughput": lambda: throughput.main([*(["--quick"] if tiny else []), "--out", str(results / "throughput.json")]),
        "quality": lambda: quality.main(["--models", "floor", *([] if tiny else shipped), *t, "--threads", str(threads),
                                         "--out", str(results)]),
        "geometry": lambda: geometry.main(["--models", "floor", "stereo", *([] if tiny else [m for m in GEOMETRY_MODELS[1:]
                                                                                  if m in shipped]),
                                           *t, "--threads", str(threads), "--out", str(results)]),
        "mesh_fps": lambda: measure(BenchConfig(quick=tiny, threads=2, out=results / "mesh_fps.json")),
        "mesh_path": lambda: mesh_path.main([*t, "--threads", str(threads), "--out", str(results)]),
        "lift": lambda: lift.main([*t, "--threads", str(threads), "--out", str(results)]),
        "lift_extra": lambda: lift_extra.main([*t, "--threads", str(threads), "--out", str(results)]),
        "geometry_budget": lambda: geometry_budget.main([*t, "--threads", str(threads), "--out", str(results)]),
        "ablation": lambda: ablation_gpnr.main([*t, "--threads", str(threads),
                                                "--out", str(results / "ablation_gpnr.json")]),
        "poses": lambda: _run_poses(results, tiny, threads),
        "reliability": lambda: reliability.main([*(["--fuzz-examples", "50", "--kills", "1", "--signals", "1",
                                                    "--pairs", "1"] if tiny else []),
                                                 "--out", str(results / "reliability.json")]),
        "fast_paths": lambda: fast_paths.main(["--out", str(results / "fast_paths.json")]),
        "peer_ibrnet": lambda: peer_ibrnet.main([*(["--ibrnet-root", peer_root] if peer_root else []),
                                                 *(["--width", "24", "--height", "18", "--train-rays", "32",
                                                    "--train-steps", "1"] if tiny else []), "--reference-too",
                                                 "--out", str(results / "peer_ibrnet.json")]),
        "tiny_levers": lambda: tiny_levers.main(["--out", str(results / "tiny_levers.json")]),
        "compile_cache": lambda: compile_cache.main(["--out", str(results / "compile_cache.json")]),
        "end_to_end": lambda: end_to_end.main(["--demo", "--reconstruct", str(ROOT.parent / "shared" / "data" / "llff"
                                                                          / "fern" / "images_12"),
                                               "--out", str(results / "end_to_end.json")]),
    }
    then = {  # a second run under the same step name
        # the reference's evaluation configuration: 10 views of 1008x756, a window rendered, render only
        "peer_ibrnet": lambda: peer_ibrnet.main([*(["--ibrnet-root", peer_root] if peer_root else []), "--width",
                                                 "1008", "--height", "756", "--views", "10", "--crop", "64", "32",
                                                 "--train-steps", "0", "--reference-too",
                                                 "--out", str(results / "peer_ibrnet_eval.json")]) if not tiny else None,
        "tiny_levers": lambda: tiny_levers.main(["--switches", "--rounds", "1", "--out", str(results / "switches.json")]),
    }
    for step in steps:
        print(f"== bench step {step}", flush=True)
        runs[step]()
        if step in then:
            then[step]()


def _run_poses(results: Path, tiny: bool, threads: int) -> None:
    """`python -m bench poses`, when pycolmap (the `capture` extra) is installed."""
    try:
        import pycolmap  # noqa: F401
    except ImportError:
        print("skipping poses: pycolmap is not installed (pip install -e '.[capture]')")
        return
    from bench import poses

    poses.main([*(["--tiny"] if tiny else []), "--threads", str(threads), "--out", str(results / "poses.json")])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reuse", action="store_true", help="do not run benchmarks; rewrite the page only")
    parser.add_argument("--tiny", action="store_true", help="a fast subset (for tests)")
    parser.add_argument("--only", nargs="+", choices=STEPS, default=None,
                        help="run only these benchmarks (default: all; with --tiny: " + " ".join(TINY_STEPS) + ")")
    parser.add_argument("--skip", nargs="+", choices=STEPS, default=(), help="benchmarks not to run")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of the quality/geometry/lift runs")
    parser.add_argument("--results", type=Path, default=HERE / "results")
    parser.add_argument("--out", type=Path, default=ROOT / "BENCHMARKS.md")
    args = parser.parse_args(argv)
    if not args.reuse:
        steps = tuple(x for x in (args.only or (TINY_STEPS if args.tiny else STEPS)) if x not in args.skip)
        run_benchmarks(args.results, args.tiny, tuple(x for x in STEPS if x in steps), args.threads)
    write_page(args.results, args.out)
    print(f"wrote {args.out}")
