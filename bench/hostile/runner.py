"""The hostile set's runner: every case of every class (in a fixed order: ``--limit N`` runs the first N), each in a
forked child with a time limit and an address-space limit, judged by its exit code, its stderr and the fixtures'
state before and after; ``main`` writes ``bench/results/hostile.json``."""

from __future__ import annotations

import argparse
import importlib
import json
import os
import resource
import signal
import stat
import sys
import tempfile
import time
from pathlib import Path

from bench.hostile.files import file_cases
from bench.hostile.fixtures import build
from bench.hostile.folders import folder_cases, valid_folder_cases
from bench.hostile.numbers import number_cases
from bench.hostile.options import memory_cases, option_cases
from bench.hostile.outputs import output_cases, user_file_cases
from bench.hostile.photos import photo_cases
from bench.hostile.resume import resume_cases
from bench.hostile.video import capture_cases, video_cases
from bench.hostile.viewer import http_case, request_cases, viewer_cases

BENCH = Path(__file__).resolve().parents[1]

TIMEOUT = 60.0
"""Seconds before a case counts as a hang."""
EXTRA_MEMORY = 6 * 2**30
"""Address space a case may add to the parent's before it counts as killed for memory."""


def cases(p: dict[str, Path], work: Path) -> list[dict]:
    """Every case: ``{"class", "args", "named" (text the message must hold) or None, "accept" (exit 0 wanted)}``."""
    return (number_cases(p) + photo_cases(p, work) + file_cases(p, work) + output_cases(p) + viewer_cases()
            + user_file_cases(p, work) + capture_cases(work) + memory_cases(p) + fresh_cases(p, work))


def fresh_cases(p: dict[str, Path], work: Path) -> list[dict]:
    """The set written for the verbs and options added since the classes above (issue 46 item 4)."""
    return (video_cases(work) + valid_folder_cases(work) + folder_cases(work) + option_cases(p, work)
            + resume_cases(p, work) + request_cases())


def _tree(root: Path) -> dict[str, tuple]:
    out = {}
    for dirpath, dirs, files in os.walk(root):
        for n in dirs + files:
            q = Path(dirpath) / n
            st = os.lstat(q)
            # a folder's own time changes with a lock file made and removed in it: its entries are compared
            out[str(q.relative_to(root))] = (st.st_mode, st.st_size, 0 if stat.S_ISDIR(st.st_mode) else st.st_mtime_ns)
    return out


def _state(path: Path):
    """What a user's file, link or folder (its entries) is, for a before/after comparison (None: gone)."""
    if not path.exists() and not path.is_symlink():
        return None
    if path.is_dir() and not path.is_symlink():
        return _tree(path)
    st = os.lstat(path)
    return st.st_mode, st.st_size, st.st_mtime_ns, os.readlink(path) if path.is_symlink() else None


def _child(argv: list[str], cwd: Path, err: Path, limit: int) -> None:
    os.chdir(cwd)
    fd = os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    os.dup2(fd, 2)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    sys.stderr = os.fdopen(2, "w", buffering=1)
    sys.stdout = os.fdopen(1, "w")
    rc = 1
    try:
        if argv[0] == "inspect_photos":  # valid unusual photos: stage them as process does (COLMAP not run)
            from omnirecon.capture.images import stage_images
            stage_images(Path(argv[1]), cwd / "staged", shared_camera=argv[2:] != ["per_image"])
            import shutil
            shutil.rmtree(cwd / "staged")
            rc = 0
        elif argv[0] == "probe_video":  # a valid clip: sampled as process samples it, upright, at its shown size
            from PIL import Image

            from omnirecon.capture.video import sample_frames

            names = sample_frames(Path(argv[1]), cwd / "staged", fps=4)
            size = Image.open(cwd / "staged" / names[0]).size
            import shutil
            shutil.rmtree(cwd / "staged")
            rc = 0 if size == (int(argv[2]), int(argv[3])) and len(names) >= 10 else 3
            print(f"{len(names)} frames of {size[0]}x{size[1]}", file=sys.stderr)
        elif argv[0].startswith("http_"):
            rc = http_case(argv)
        else:
            from omnirecon.cli import main
            rc = main(argv)
    except BaseException:  # noqa: BLE001 - what escapes main is what a user would see
        import traceback
        traceback.print_exc()
        rc = 1
    sys.stderr.flush()
    os._exit(rc if isinstance(rc, int) else 1)



def run_case(case: dict, p: dict[str, Path], work: Path, limit: int) -> dict:
    cwd = Path(tempfile.mkdtemp(prefix="cwd_", dir=work))
    out = cwd.parent / (cwd.name + "_out")
    argv = [a.replace("{out}", str(out)) for a in case["args"]]
    named = case["named"].replace("{out}", str(out)) if case["named"] else None
    users = case["setup"](out) if case.get("setup") else []  # what the user (or a crash) left at OUT before the run
    users_before = [_state(u) for u in users]
    err = work / "stderr.txt"
    before = _tree(p["root"])
    t0 = time.perf_counter()
    pid = os.fork()
    if pid == 0:
        _child(argv, cwd, err, limit)
    status, verdict = None, None
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.perf_counter() - t0 > TIMEOUT:
            os.kill(pid, signal.SIGKILL)  # our own child
            os.waitpid(pid, 0)
            verdict = "hang"
            break
        time.sleep(0.02)
    seconds = time.perf_counter() - t0
    text = err.read_text(errors="replace") if err.exists() else ""
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    rc = os.waitstatus_to_exitcode(status) if verdict is None else None
    changed = _tree(p["root"]) != before or [_state(u) for u in users] != users_before
    kept = "rerun the same command to continue" in text  # reconstruct keeps its finished stages in OUT.partial, and says so
    leftovers = [str(q) for q in cwd.parent.glob(out.name + "*") if not (kept and q.name == f"{out.name}.partial")
                 and q not in users] + \
        [str(q) for q in cwd.rglob("*")]
    if verdict is None:
        if rc is not None and rc < 0:
            verdict = "killed"
        elif "MemoryError" in text:
            verdict = "memory"
        elif changed:
            verdict = "data_changed"
        elif case.get("accept") or case["class"] == "viewer" or (case.get("accept_or_refuse") and rc == 0):
            verdict = "handled" if rc == 0 and "Traceback" not in text else "not_handled"
        elif (rc == 2 and len(lines) == 1 and lines[0].startswith("omnirecon: error: ") and "(fix: " in lines[0]
              and "Traceback" not in text and not leftovers and named in lines[0]):
            verdict = "handled"
        else:
            verdict = "not_handled"
    return {"class": case["class"], "args": [a.replace(str(p["root"]), "<fx>").replace(str(work), "<work>")
                                             for a in argv],
            "verdict": verdict, "exit": rc, "seconds": round(seconds, 2), "lines": len(lines),
            "message": (lines[-1] if lines else "")[:300].replace(str(work), "<work>"), "leftovers": len(leftovers)}


def _vm_bytes() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    return 0


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=importlib.import_module("bench.hostile").__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=BENCH / "results" / "hostile.json")
    parser.add_argument("--limit", type=int, default=None, help="run only the first N cases (a quick look)")
    parser.add_argument("--only", default=None, help="only cases of these classes (comma-separated)")
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    from omnirecon.cli import COMMANDS, _load
    from omnirecon.provenance import provenance

    for spec in COMMANDS.values():  # imported once: every forked case starts warm
        _load(spec)
    import omnirecon.capture.images  # noqa: F401
    import omnirecon.viewer.server  # noqa: F401

    work = Path(tempfile.mkdtemp(prefix="hostile_"))
    p = build(work / "fx")
    todo = cases(p, work / "fx" / "cases")
    if args.only:
        todo = [c for c in todo if c["class"] in args.only.split(",")]
    todo = todo[: args.limit] if args.limit else todo
    limit = _vm_bytes() + EXTRA_MEMORY
    t0 = time.perf_counter()
    results = []
    for i, case in enumerate(todo):
        r = run_case(case, p, work, limit)
        results.append(r)
        if r["verdict"] != "handled":
            print(f"[{i + 1}/{len(todo)}] {r['verdict']}: {' '.join(r['args'])[:160]}\n    {r['message'][:200]}",
                  flush=True)
    per: dict[str, dict] = {}
    for r in results:
        c = per.setdefault(r["class"], {"cases": 0, "handled": 0})
        c["cases"] += 1
        c["handled"] += r["verdict"] == "handled"
    verdicts = {v: sum(r["verdict"] == v for r in results) for v in
                ("handled", "not_handled", "data_changed", "hang", "memory", "killed")}
    record = {"provenance": provenance(seed=0, load_average=os.getloadavg()), "cases": len(results),
              "handled": verdicts["handled"], "handled_fraction": verdicts["handled"] / max(1, len(results)),
              "verdicts": verdicts, "per_class": per, "seconds": round(time.perf_counter() - t0, 1),
              "timeout_s": TIMEOUT, "extra_memory_gb": EXTRA_MEMORY / 2**30,
              "failures": [r for r in results if r["verdict"] != "handled"],
              "results": [{"class": r["class"], "verdict": r["verdict"], "exit": r["exit"], "seconds": r["seconds"],
                           "args": " ".join(r["args"])[:200], "message": r["message"][:160]} for r in results]}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1, default=str))
    print(f"{record['handled']}/{record['cases']} handled ({100 * record['handled_fraction']:.1f} %); "
          f"{verdicts}; {record['seconds']} s -> {args.out}")
    import shutil
    shutil.rmtree(work, ignore_errors=True)
    return record

