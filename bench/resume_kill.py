"""`reconstruct` killed with SIGKILL at every stage, then rerun: the final output against an uninterrupted run's.

    python -m bench resume_kill                 # 12 procedural photos (128 px), ~15 min at 1 thread
    python -m bench resume_kill --grid 0        # only the kills at the stage marks

A run of ``reconstruct`` on a folder of 12 procedural photos (``tests/conftest.procedural_photos``: `process` poses
them) is started and killed with SIGKILL (a) as soon as each stage is recorded as finished in ``OUT.partial``
(``.omnirecon-partial/stages.json``) and as the finished run swaps its folder in (the marker written), and (b) at
``--grid`` evenly spaced times over an uninterrupted run's length (any moment of any stage). The same command is then
rerun to its end, and every file of its output is compared with an uninterrupted run's: bytes, JSON records but for
their timings (keys naming seconds, provenance, peak memory, resumed stages, FPS, the time written), the report page
only by name (it shows timings). A second uninterrupted run is compared the same way first (what the comparison
allows when nothing was killed). Writes ``bench/results/resume_kill.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from omnirecon.outputs import kept_stages

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SMALL = ["--resolution", "32", "--mesh-resolution", "32", "--finetune-seconds", "0", "--frames", "2", "--no-viewer",
         "--threads", "1"]
TIMING = ("seconds", "provenance", "peak_rss_mb", "resumed", "fps", "written")
"""Record keys that hold times (or say when and how fast): the only part of an output a rerun may change."""
MARKS = ("process", "mesh", "finetune", "export", "finish")
"""Kill points by stage: just after the stage is recorded as finished (``finish``: the marker is written)."""


def start_cli(args: list, cwd: Path) -> subprocess.Popen:
    """``omnirecon ARGS`` started in ``cwd`` from this checkout (one thread), its output piped."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "omnirecon.cli", *map(str, args)], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _untimed(value):
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items() if not any(t in k for t in TIMING)}
    return [_untimed(v) for v in value] if isinstance(value, list) else value


def differences(a: Path, b: Path) -> list[str]:
    """The files in which two reconstruct outputs differ (see the module docstring); [] when alike."""
    fa = {str(p.relative_to(a)): p for p in sorted(a.rglob("*")) if p.is_file()}
    fb = {str(p.relative_to(b)): p for p in sorted(b.rglob("*")) if p.is_file()}
    out = sorted(set(fa) ^ set(fb))
    for name in sorted(set(fa) & set(fb)):
        if name.endswith(".json"):
            same = _untimed(json.loads(fa[name].read_text())) == _untimed(json.loads(fb[name].read_text()))
        else:
            same = name.endswith("index.html") or fa[name].read_bytes() == fb[name].read_bytes()
        if not same:
            out.append(name)
    return out


def killed_run(cmd: list, cwd: Path, out: Path, mark: str | None, at: float | None) -> dict:
    """Start ``cmd``, SIGKILL it at stage ``mark`` or ``at`` seconds, rerun it to its end; what was kept, the rerun."""
    partial = out.parent / f"{out.name}.partial"
    proc, t0 = start_cli(cmd, cwd), time.monotonic()
    while proc.poll() is None:
        kept = kept_stages(partial)
        if mark == "finish" and (partial / ".omnirecon-output.json").is_file() or mark in kept \
                or at is not None and time.monotonic() - t0 >= at:
            break
        time.sleep(0.01)
    ended = proc.poll() is not None
    if not ended:
        proc.send_signal(signal.SIGKILL)  # our own child
    proc.communicate(timeout=120)
    state = {"killed_at_s": round(time.monotonic() - t0, 2), "ended_before_kill": ended, "kept": kept_stages(partial),
             "output_existed": out.exists()}
    if ended:  # the run outlived its kill (a faster run than the reference): its output is compared as it is
        return {**state, "rerun_exit": None, "rerun_seconds": 0.0, "rerun_said": [], "rerun_error": None}
    t1 = time.monotonic()
    rerun = start_cli(cmd, cwd)
    stdout, stderr = rerun.communicate(timeout=1800)
    return {**state, "rerun_exit": rerun.returncode, "rerun_seconds": round(time.monotonic() - t1, 1),
            "rerun_said": [ln for ln in stdout.splitlines() if "continuing from" in ln or "starting over" in ln],
            "rerun_error": stderr.strip().splitlines()[-1][:300] if rerun.returncode else None}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE / "results" / "resume_kill.json")
    parser.add_argument("--grid", type=int, default=6, help="kills at evenly spaced times of an uninterrupted run")
    parser.add_argument("--views", type=int, default=12)
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import procedural_photos

    from omnirecon.provenance import provenance

    work = Path(tempfile.mkdtemp(prefix="resume_kill_"))
    try:
        photos = procedural_photos(work, 128, args.views)
        runs: dict[str, dict] = {}
        t0 = time.monotonic()
        whole = work / "whole"
        done = start_cli(["reconstruct", photos, "--out", whole, *SMALL], work).communicate(timeout=1800)
        length = time.monotonic() - t0
        if not (whole / "reconstruct.json").is_file():
            raise SystemExit(f"the uninterrupted run failed: {done[1][-2000:]}")
        again = work / "again"
        start_cli(["reconstruct", photos, "--out", again, *SMALL], work).communicate(timeout=1800)
        baseline = differences(whole, again)
        points = [(m, None) for m in MARKS] + [(None, round(length * (i + 1) / (args.grid + 1), 1))
                                               for i in range(args.grid)]
        for mark, at in points:
            name = f"after {mark}" if mark else f"at {at} s"
            out = work / f"rec_{len(runs)}"
            r = killed_run(["reconstruct", photos, "--out", out, *SMALL], work, out, mark, at)
            r["differs"] = differences(whole, out) if r["rerun_exit"] in (0, None) else None
            r["same"] = r["differs"] == []
            runs[name] = r
            print(f"{name}: killed at {r['killed_at_s']} s with {r['kept']} kept; rerun exit {r['rerun_exit']} in "
                  f"{r['rerun_seconds']} s; same output: {r['same']} {r['differs'] or ''}", flush=True)
        record = {"provenance": provenance(seed=0, load_average=os.getloadavg()), "photos": args.views,
                  "photo_px": 128, "args": SMALL, "uninterrupted_seconds": round(length, 1),
                  "uninterrupted_twice_differs": baseline, "kills": len(runs),
                  "same_output": sum(r["same"] for r in runs.values()), "runs": runs}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1, default=str))
    print(f"{record['same_output']}/{record['kills']} killed runs rerun to the uninterrupted output "
          f"(two uninterrupted runs differ in {baseline or 'nothing'}); -> {args.out}")
    return record
