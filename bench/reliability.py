"""Reliability counts for BENCHMARKS.md: the malformed-input table, the fuzz run and kill -9 recovery.

    python bench/reliability.py                           # table + 10,000 fuzz cases per target + kills
    python bench/reliability.py --fuzz-examples 200 --kills 2   # a quick run

* **Malformed inputs**: runs ``tests/commands/test_malformed.py`` (every command against a table of malformed
  inputs: exit 2, one line naming the file with a fix clause, no traceback, nothing written) and
  counts the rows per command and how many were handled.
* **Fuzzing**: runs ``tests/data/test_fuzz.py`` with ``OMNIRECON_FUZZ_EXAMPLES`` cases per target (7 scene
  readers, ``meta.json``, ``model.safetensors``) and records cases, InputErrors, successful reads and
  failures (any other exception) per target.
* **kill -9**: starts ``omnirecon synth``, ``train``, ``mesh`` and ``export`` (``--kills`` times each),
  sends SIGKILL after a random delay, then runs the same command again to completion and counts hidden
  leftovers (temporaries of our naming) and incomplete results (a mesh set with members missing, a
  scene without its ``scene.json``).

Writes ``bench/results/reliability.json`` with a provenance header; ``bench/run_all.py`` renders it.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
TESTS = ROOT / "tests"


def _pytest(args: list[str], env: dict, timeout: float) -> tuple[int, Path]:
    junit = Path(tempfile.mkdtemp(prefix="reliability_")) / "junit.xml"
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={junit}", *args]
    proc = subprocess.run(cmd, cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": "1", **env}, timeout=timeout,
                          capture_output=True, text=True)
    print(proc.stdout[-2000:], proc.stderr[-2000:], sep="\n", flush=True)
    return proc.returncode, junit


def malformed_counts(junit: Path | None = None) -> dict:
    """Rows of tests/test_malformed.py per command, and how many passed (were handled); ``junit``: count
    from that JUnit XML of an earlier run instead of running the table."""
    if junit is None:
        _, junit = _pytest([str(TESTS / "commands" / "test_malformed.py"), "-k", "test_malformed_input"], {}, 1800)
    per: dict[str, list[int]] = {}
    failed = []
    for case in ET.parse(junit).getroot().iter("testcase"):
        m = re.search(r"\[\d+-([^\s\]]+)", case.get("name", ""))
        cmd = m.group(1) if m else "?"
        ok = case.find("failure") is None and case.find("error") is None and case.find("skipped") is None
        row = per.setdefault(cmd, [0, 0])
        row[0] += 1
        row[1] += int(ok)
        if not ok:
            failed.append(case.get("name"))
    return {"cases": sum(r[0] for r in per.values()), "handled": sum(r[1] for r in per.values()),
            "per_command": {k: {"cases": v[0], "handled": v[1]} for k, v in sorted(per.items())}, "failed": failed}


def fuzz_counts(examples: int) -> dict:
    report = Path(tempfile.mkdtemp(prefix="reliability_")) / "fuzz.json"
    rc, _ = _pytest([str(TESTS / "data" / "test_fuzz.py")], {"OMNIRECON_FUZZ_EXAMPLES": str(examples),
                                                     "OMNIRECON_FUZZ_REPORT": str(report)}, 6 * 3600)
    targets = json.loads(report.read_text()) if report.is_file() else {}
    return {"examples_per_target": examples, "targets": targets, "cases": sum(t["cases"] for t in targets.values()),
            "failures": sum(t["failures"] for t in targets.values()), "pytest_exit": rc}


# ---------------------------------------------------------------------- kill -9
STALE = re.compile(r"^\..+\.(?:pid|tmp)(\d+)(?:\..*)?$")


def _hidden_leftovers(folder: Path) -> list[str]:
    return [str(p.relative_to(folder)) for p in folder.rglob(".*") if STALE.match(p.name)]


def _cli(args: list[str]) -> list[str]:
    return [sys.executable, "-m", "omnirecon.cli", *args]


def _kill_after(cmd: list[str], delay: float, env: dict) -> bool:
    """Start ``cmd``, SIGKILL it after ``delay`` s; whether it was still running then."""
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        proc.wait(delay)
        return False
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        return True


def kill_runs(kills: int, seed: int = 0, only: list[str] | None = None) -> dict:
    """``kills`` SIGKILLs into each command at a moment drawn uniformly in 5-75 % of the duration of one
    uninterrupted run (measured first; shortened when a run finishes before its kill, and tries go on until
    ``kills`` landed, at most ``3 * kills``), each from an empty output (train: an empty run folder), then the
    same command again to completion (train: ``--resume`` when a checkpoint survived)."""
    import shutil

    rng = random.Random(seed)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    work = Path(tempfile.mkdtemp(prefix="reliability_kill_"))
    scene_dir = work / "scenes"
    subprocess.run(_cli(["synth", "--num-scenes", "1", "--views", "10", "--resolution", "32", "--out", str(scene_dir)]),
                   cwd=ROOT, env=env, check=True, capture_output=True)
    scene = next(scene_dir.glob("scene_*"))
    ckpt = ROOT / "checkpoints" / "omnirecon-tiny"
    tiny = ["--model", "gpnr-tiny", "--model-overrides", "num_samples=8", "dim=32", "mlp_dim=32", "heads=1",
            "layers=[1,1,1]", "point_freqs=4", "--num-views", "3", "--resolution", "32", "--rays", "64",
            "--val-every", "0", "--threads", "1", "--no-progress", "--ckpt-every", "3"]
    commands = {
        "synth": lambda out: ["synth", "--num-scenes", "2", "--views", "8", "--resolution", "48", "--workers", "1",
                              "--out", str(out)],
        "train": lambda out: ["train", "--data", str(scene), "--steps", "12", "--out", str(out),
                              "--cache", str(work / "cache"), *tiny],
        "mesh": lambda out: ["mesh", "--scene", str(scene), "--model", "floor", "--threads", "1",
                             "--out", str(out / "m.ply"), str(out / "m.obj"), str(out / "m.glb")],
    }
    if ckpt.is_dir():
        from omnirecon.viewer.bundle import three_unavailable_reason

        viewer = ["--no-viewer"] if three_unavailable_reason() else []  # the mesh files only, without three.js
        commands["export"] = lambda out: ["export", "--scene", str(scene), "--ckpt", str(ckpt), "--threads", "1",
                                          "--device", "cpu", "--resolution", "32", *viewer, "--out", str(out)]
    try:  # photos without poses: a small procedural capture, its images only
        import pycolmap  # noqa: F401

        photos = work / "photos"
        photos.mkdir()
        subprocess.run(_cli(["synth", "--num-scenes", "1", "--views", "12", "--resolution", "256", "--rig", "frontal",
                             "--out", str(work / "capture")]), cwd=ROOT, env=env, check=True, capture_output=True)
        for img in sorted(next((work / "capture").glob("scene_*")).glob("*/r_*.png")):
            if img.stem[2:].isdigit():  # the colour images, not depth, normal, label or mask maps
                shutil.copy(img, photos / f"{img.parent.name}_{img.name}")
        commands["process"] = lambda out: ["process", str(photos), "--out", str(out / "scene")]
    except ImportError:
        pass
    results = {}
    for name, make in commands.items():
        if only and name not in only:
            continue
        out = work / name
        t0 = time.perf_counter()
        subprocess.run(_cli(make(out)), cwd=ROOT, env=env, check=True, capture_output=True)
        duration = time.perf_counter() - t0
        rec = {"kills": 0, "finished_before_kill": 0, "incomplete_after_kill": 0, "leftovers_after_rerun": 0,
               "rerun_failed": 0, "uninterrupted_s": round(duration, 1)}
        for _ in range(3 * kills):  # until `kills` SIGKILLs landed while the command was running
            if rec["kills"] >= kills:
                break
            shutil.rmtree(out, ignore_errors=True)
            start = time.perf_counter()
            killed = _kill_after(_cli(make(out)), rng.uniform(0.05, 0.75) * duration, env)
            rec["kills" if killed else "finished_before_kill"] += 1
            if not killed:  # this run was quicker than the measured one: aim earlier from now on
                duration = min(duration, time.perf_counter() - start)
            rec["incomplete_after_kill"] += int(_incomplete(name, out))
            resume = name == "train" and (out / "checkpoints" / "latest").exists()
            rerun = subprocess.run(_cli(make(out) + (["--resume"] if resume else [])), cwd=ROOT, env=env,
                                   capture_output=True, text=True)
            rec["rerun_failed"] += int(rerun.returncode != 0)
            if rerun.returncode != 0:
                rec.setdefault("rerun_errors", []).append(rerun.stderr.strip()[-300:])
            rec["leftovers_after_rerun"] += len(_hidden_leftovers(out))
        results[name] = rec
        print(f"kill -9 {name}: {rec}", flush=True)
    return results


def _incomplete(name: str, out: Path) -> bool:
    """A partial result that looks complete: a mesh set with some members missing, a scene folder
    without its scene.json (written last), a checkpoint folder whose meta.json (written last) is absent
    while weights are present."""
    if name == "mesh":
        present = [(out / f"m.{x}").is_file() for x in ("ply", "obj", "glb")]
        return any(present) and not all(present)
    if name == "synth":
        return any(p.is_dir() and not (p / "scene.json").is_file() for p in out.glob("scene_*"))
    if name == "train":
        return any((p / "model.safetensors").is_file() and not (p / "meta.json").is_file()
                   for p in (out / "checkpoints").glob("step_*"))
    if name == "export":
        return (out / "viewer").is_dir() and not (out / "viewer" / "bundle.json").is_file()
    if name == "process":  # the scene folder appears only complete (renamed from a temporary at the end)
        return (out / "scene").exists() and not (out / "scene" / "process.json").is_file()
    return False


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fuzz-examples", type=int, default=10_000, help="fuzz cases per target")
    parser.add_argument("--kills", type=int, default=10, help="SIGKILLs per command (0: skip)")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "reliability.json")
    parser.add_argument("--rerun", nargs="+", default=None, metavar="TARGET",
                        help="fuzz only these targets again (after fixing what a run found) and append the counts to "
                             "--out as a rerun at the current commit, with --why")
    parser.add_argument("--kills-only", action="store_true", help="rerun only the kill -9 part into --out")
    parser.add_argument("--commands", nargs="+", default=None, help="with --kills-only: only these commands (the "
                        "others keep their counts in --out)")
    parser.add_argument("--malformed-only", action="store_true", help="recount only the malformed-input table into --out")
    parser.add_argument("--why", default="fixes", help="what changed since the run in --out (with --rerun)")
    args = parser.parse_args(argv)
    from omnirecon.data.io import write_json
    from omnirecon.provenance import git_commit, provenance

    if args.kills_only:  # replace the kill counts of an existing results file, at the current commit
        result = json.loads(args.out.read_text())
        counts = kill_runs(args.kills, only=args.commands)
        result["kill"] = {**result.get("kill", {}), **counts} if args.commands else counts
        result.setdefault("kill_provenance_by_command", {}).update(
            {name: provenance(seed=0, kills=args.kills) for name in counts})
        result["kill_provenance"] = provenance(seed=0, kills=args.kills)
        write_json(args.out, result)
        print(f"wrote {args.out}")
        return result
    if args.malformed_only:
        result = json.loads(args.out.read_text())
        result["malformed"] = malformed_counts()
        result["malformed_provenance"] = provenance(seed=0)
        write_json(args.out, result)
        print(f"malformed inputs: {result['malformed']['handled']}/{result['malformed']['cases']}; wrote {args.out}")
        return result
    if args.rerun:
        result = json.loads(args.out.read_text())
        report = Path(tempfile.mkdtemp(prefix="reliability_")) / "fuzz.json"
        _pytest([str(TESTS / "data" / "test_fuzz.py"), "-k", " or ".join(args.rerun)],
                {"OMNIRECON_FUZZ_EXAMPLES": str(args.fuzz_examples), "OMNIRECON_FUZZ_REPORT": str(report)}, 6 * 3600)
        targets = {k: v for k, v in json.loads(report.read_text()).items() if k in args.rerun}
        result.setdefault("fuzz_reruns", []).append({"commit": git_commit(), "why": args.why, "targets": targets,
                                                     "examples_per_target": args.fuzz_examples,
                                                     "provenance": provenance(seed=0)})
        write_json(args.out, result)
        print(f"rerun {targets}; wrote {args.out}")
        return result

    start = time.perf_counter()
    result = {"provenance": provenance(seed=0, fuzz_examples=args.fuzz_examples, kills=args.kills,
                                       command="python bench/reliability.py " + " ".join(argv or sys.argv[1:]))}
    result["malformed"] = malformed_counts()
    result["fuzz"] = fuzz_counts(args.fuzz_examples)
    if args.kills > 0:
        result["kill"] = kill_runs(args.kills)
    result["seconds"] = round(time.perf_counter() - start, 1)
    write_json(args.out, result)
    m, f = result["malformed"], result["fuzz"]
    print(f"malformed inputs: {m['handled']}/{m['cases']} handled; fuzz: {f['cases']} cases, {f['failures']} failures; "
          f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
