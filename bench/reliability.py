"""Reliability counts for BENCHMARKS.md: the malformed-input table, the fuzz run and kill -9 recovery.

    python -m bench reliability                           # table + 10,000 fuzz cases per target + kills
    python -m bench reliability --fuzz-examples 200 --kills 2   # a quick run

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
* **Output sets under kill -9 and Ctrl-C** (``--outputs-only``): ``mesh``, ``render`` and ``reconstruct`` replace
  a previous output of theirs (variants A and B alternate: other frame counts or resolutions), SIGKILL or
  SIGINT lands at a random moment; the output must then be the old set or the complete new one, never a
  mix; the re-run must succeed and leave no temporaries or locks.
* **Concurrent runs** (``--outputs-only``): two runs of ``render``, ``mesh``, ``train``, ``reconstruct`` (and
  ``process`` with pycolmap) started together on one ``--out``: one must finish, the other must be refused
  with the one-line lock message, and the output must be one complete set.

Writes ``bench/results/reliability.json`` with a provenance header; ``bench/report/reliability.py`` renders it.

Size: five measurements of one kind (run commands, break them, count what survived) that share their
helpers; split by measurement they would import each other's.
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


# ---------------------------------------------------------------------- output sets: signals and concurrent runs
def _ply_faces(path: Path) -> int | None:
    try:
        head = path.read_bytes()[:2000].split(b"end_header")[0].decode(errors="replace")
    except OSError:
        return None
    m = re.search(r"element face (\d+)", head)
    return int(m.group(1)) if m else None


def _set_state(name: str, out: Path, variants: dict) -> str:
    """Which complete set ``out`` holds: ``"a"`` or ``"b"`` (the variant's own numbers, every member present and
    agreeing with the others), else ``"mixed"`` (members missing or from two runs) or ``"absent"``."""
    if not out.exists():
        return "absent"
    try:
        if name == "render":
            frames = len(list((out / "frames").glob("*.png")))
            cams = len(json.loads((out / "cameras.json").read_text())["frames"])
            whole = (out / "video.mp4").is_file() and frames == cams
            key = frames
        elif name == "mesh":
            metrics = json.loads((out / "m_metrics.json").read_text())
            final = metrics["faces"].get("decimated", metrics["faces"]["components"])
            whole = all(Path(f).is_file() for f in metrics["files"]) and _ply_faces(out / "m.ply") == final
            key = metrics["resolution"][0]
        elif name == "reconstruct":
            rec = json.loads((out / "reconstruct.json").read_text())
            whole = all((out / p).is_file() for p in ("index.html", "path.mp4", "mesh.ply", "finetune/curve.json",
                                                      "export/mesh.glb", ".omnirecon-output.json"))
            key = rec["path"]["frames"]
        else:
            raise ValueError(name)
    except (OSError, ValueError, KeyError, TypeError):
        return "mixed"
    for v, k in variants.items():
        if whole and key == k:
            return v
    return "mixed"


def _leftovers(out: Path) -> list[str]:
    """Temporaries of our naming and lock files inside ``out`` or beside it under its name."""
    inside = [p for p in out.rglob(".*") if STALE.match(p.name) or p.name.endswith(".lock")] if out.is_dir() else []
    beside = [p for p in out.parent.glob(f".{out.name}*")]
    return [str(p) for p in inside + beside]


def _signal_after(cmd: list[str], delay: float, sig: int, env: dict) -> tuple[bool, int]:
    """Start ``cmd``, send ``sig`` after ``delay`` s; (whether it was still running then, its exit code)."""
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        return False, proc.wait(delay)
    except subprocess.TimeoutExpired:
        proc.send_signal(sig)
        try:
            return True, proc.wait(300)
        except subprocess.TimeoutExpired:  # did not stop on the signal: counted as a hang (code None)
            proc.kill()
            proc.wait()
            return True, -999


def _output_commands(work: Path, env: dict) -> tuple[Path, dict]:
    scene_dir = work / "scenes"
    subprocess.run(_cli(["synth", "--num-scenes", "1", "--views", "10", "--resolution", "32", "--out", str(scene_dir)]),
                   cwd=ROOT, env=env, check=True, capture_output=True)
    scene = next(scene_dir.glob("scene_*"))
    ckpt = ROOT / "checkpoints" / "omnirecon-tiny"
    commands = {  # name: (make(out, variant value), {variant: value})
        "render": (lambda out, n: ["render", "--scene", str(scene), "--model", "floor", "--resolution", "32",
                                   "--num-views", "3", "--threads", "1", "--frames", str(n), "--out", str(out)],
                   {"a": 3, "b": 6}),
        "mesh": (lambda out, r: ["mesh", "--scene", str(scene), "--model", "floor", "--threads", "1", "--resolution",
                                 str(r), "--out", str(out / "m.ply"), str(out / "m.obj"), str(out / "m.glb")],
                 {"a": 24, "b": 32}),
    }
    if ckpt.is_dir():
        commands["reconstruct"] = (
            lambda out, n: ["reconstruct", str(scene), "--ckpt", str(ckpt), "--out", str(out), "--overwrite",
                            "--mesh-resolution", "32", "--resolution", "32", "--finetune-seconds", "2",
                            "--frames", str(n), "--no-viewer", "--threads", "1", "--device", "cpu"],
            {"a": 4, "b": 6})
    return scene, commands


def signal_runs(tries: int, sig: int, seed: int = 0, only: list[str] | None = None) -> dict:
    """``tries`` signals ``sig`` into runs of mesh / render / reconstruct that replace a previous output of
    theirs, each at a moment drawn in 5-75 % of an uninterrupted run; counts what the output then holds (the
    old set, the complete new one, or a mix), then re-runs the new variant to completion."""
    import shutil

    rng = random.Random(seed)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    work = Path(tempfile.mkdtemp(prefix="reliability_sets_"))
    _, commands = _output_commands(work, env)
    results = {}
    for name, (make, variants) in commands.items():
        if only and name not in only:
            continue
        out = work / name
        t0 = time.perf_counter()
        subprocess.run(_cli(make(out, variants["a"])), cwd=ROOT, env=env, check=True, capture_output=True)
        duration = time.perf_counter() - t0
        cur = _set_state(name, out, variants)
        rec = {"signals": 0, "finished_before_signal": 0, "old_set_kept": 0, "new_set_complete": 0, "mixed": 0,
               "hung": 0, "leftovers_after_rerun": 0, "rerun_failed": 0, "uninterrupted_s": round(duration, 1),
               "first_state": cur}
        for _ in range(3 * tries):
            if rec["signals"] >= tries:
                break
            nxt = "b" if cur == "a" else "a"
            start = time.perf_counter()
            landed, code = _signal_after(_cli(make(out, variants[nxt])), rng.uniform(0.05, 0.75) * duration, sig, env)
            if not landed:
                rec["finished_before_signal"] += 1
                duration = min(duration, time.perf_counter() - start)
            else:
                rec["signals"] += 1
                rec["hung"] += int(code == -999)
                state = _set_state(name, out, variants)
                rec["old_set_kept" if state == cur else "new_set_complete" if state == nxt else "mixed"] += 1
                if state not in (cur, nxt):
                    rec.setdefault("mixed_states", []).append(state)
            rerun = subprocess.run(_cli(make(out, variants[nxt])), cwd=ROOT, env=env, capture_output=True, text=True)
            ok = rerun.returncode == 0 and _set_state(name, out, variants) == nxt
            rec["rerun_failed"] += int(not ok)
            if not ok:
                rec.setdefault("rerun_errors", []).append(rerun.stderr.strip()[-300:])
            rec["leftovers_after_rerun"] += len(_leftovers(out))
            cur = nxt
        results[name] = rec
        print(f"{signal.Signals(sig).name} {name}: {rec}", flush=True)
    shutil.rmtree(work, ignore_errors=True)
    return results


def concurrent_runs(pairs: int, only: list[str] | None = None) -> dict:
    """``pairs`` times, two runs of one command started together on one fresh ``--out``: exactly one must
    finish and the other be refused by the lock (exit 2, one line naming the first run), leaving one complete
    output."""
    import shutil

    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    work = Path(tempfile.mkdtemp(prefix="reliability_concurrent_"))
    scene, commands = _output_commands(work, env)
    runs = {name: (lambda out, m=make, v=variants: m(out, v["a"]), variants) for name, (make, variants) in commands.items()}
    runs["train"] = (lambda out: ["train", "--data", str(scene), "--steps", "6", "--out", str(out), "--cache",
                                  str(work / "cache"), "--model", "gpnr-tiny", "--model-overrides", "num_samples=8",
                                  "dim=32", "mlp_dim=32", "heads=1", "layers=[1,1,1]", "point_freqs=4", "--num-views",
                                  "3", "--resolution", "32", "--rays", "64", "--val-every", "0", "--threads", "1",
                                  "--no-progress"], None)
    results = {}
    for name, (make, variants) in runs.items():
        if only and name not in only:
            continue
        rec = {"pairs": 0, "one_finished_one_refused": 0, "both_finished": 0, "both_failed": 0, "other": 0,
               "incomplete_output": 0, "leftovers": 0}
        for i in range(pairs):
            out = work / f"{name}_{i}"
            procs = [subprocess.Popen(_cli(make(out)), cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, text=True) for _ in range(2)]
            done = [(p.wait(1800), p.stderr.read()) for p in procs]
            codes = sorted(c for c, _ in done)
            refused = [e for c, e in done if c == 2]
            rec["pairs"] += 1
            if codes == [0, 2] and len(refused[0].strip().splitlines()) == 1 and "another omnirecon run" in refused[0]:
                rec["one_finished_one_refused"] += 1
            elif codes == [0, 0]:
                rec["both_finished"] += 1
            elif 0 not in codes:
                rec["both_failed"] += 1
            else:
                rec["other"] += 1
                rec.setdefault("errors", []).append([e.strip()[-300:] for _, e in done])
            if name == "train":
                complete = (out / "checkpoints" / "final" / "meta.json").is_file()
            else:
                complete = _set_state(name, out, variants) == "a"
            rec["incomplete_output"] += int(not complete)
            rec["leftovers"] += len(_leftovers(out))
            shutil.rmtree(out, ignore_errors=True)
        results[name] = rec
        print(f"concurrent {name}: {rec}", flush=True)
    shutil.rmtree(work, ignore_errors=True)
    return results


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fuzz-examples", type=int, default=10_000, help="fuzz cases per target")
    parser.add_argument("--kills", type=int, default=10, help="SIGKILLs per command (0: skip)")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "reliability.json")
    parser.add_argument("--rerun", nargs="+", default=None, metavar="TARGET",
                        help="fuzz only these targets again (after fixing what a run found) and append the counts to "
                             "--out as a rerun at the current commit, with --why")
    parser.add_argument("--kills-only", action="store_true", help="rerun only the kill -9 part into --out")
    parser.add_argument("--commands", nargs="+", default=None, help="with --kills-only / --outputs-only: only these commands (the "
                        "others keep their counts in --out)")
    parser.add_argument("--malformed-only", action="store_true", help="recount only the malformed-input table into --out")
    parser.add_argument("--why", default="fixes", help="what changed since the run in --out (with --rerun)")
    parser.add_argument("--outputs-only", action="store_true", help="rerun only the output-set signal runs (kill -9 "
                        "and SIGINT) and the concurrent runs into --out")
    parser.add_argument("--signals", type=int, default=5, help="signals per command and kind into replacing runs (0: skip)")
    parser.add_argument("--pairs", type=int, default=2, help="concurrent pairs per command (0: skip)")
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
    if args.outputs_only:  # output sets under kill -9 / Ctrl-C, and concurrent runs on one --out
        result = json.loads(args.out.read_text()) if args.out.is_file() else {"provenance": provenance(seed=0)}
        result["output_sets"] = {"SIGKILL": signal_runs(args.signals, signal.SIGKILL, only=args.commands),
                                 "SIGINT": signal_runs(args.signals, signal.SIGINT, seed=1, only=args.commands)}
        result["concurrent"] = concurrent_runs(args.pairs, only=args.commands)
        result["outputs_provenance"] = provenance(seed=0, signals=args.signals, pairs=args.pairs,
                                                  load_average=os.getloadavg())
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
                                       command="python -m bench reliability " + " ".join(argv or sys.argv[1:]))}
    result["malformed"] = malformed_counts()
    result["fuzz"] = fuzz_counts(args.fuzz_examples)
    if args.kills > 0:
        result["kill"] = kill_runs(args.kills)
    if args.signals > 0:
        result["output_sets"] = {"SIGKILL": signal_runs(args.signals, signal.SIGKILL),
                                 "SIGINT": signal_runs(args.signals, signal.SIGINT, seed=1)}
    if args.pairs > 0:
        result["concurrent"] = concurrent_runs(args.pairs)
    result["seconds"] = round(time.perf_counter() - start, 1)
    write_json(args.out, result)
    m, f = result["malformed"], result["fuzz"]
    print(f"malformed inputs: {m['handled']}/{m['cases']} handled; fuzz: {f['cases']} cases, {f['failures']} failures; "
          f"wrote {args.out}")
    return result

