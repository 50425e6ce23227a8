"""``torch.compile`` with its persistent cache: the cold start, the warm start and the steady render, in one run.

    python -m bench compile_cache                         # ibrnet-tiny, 64x64 view, 3 sources
    python -m bench compile_cache --preset ibrnet-paper --size 64 48

A user turns compilation on with ``OMNIRECON_FAST=compile=1``; inductor's kernels are kept on disk
(``TORCHINDUCTOR_CACHE_DIR``, by default ``~/.cache/omnirecon/inductor``). Each side runs in its own fresh
process, one thread, in this order: ``eager`` (the default: no compile), ``cold`` (compile with an empty cache
folder made for this run), ``warm`` (a new process, the same folder: what every later run pays), ``eager``
again. Each process renders the same view ``--renders`` times (random weights of ``--preset``, seed 0; speed
does not depend on them): the first render carries the compile, the best of the others is the steady state.
Time is process CPU seconds including the compile workers inductor starts (``RUSAGE_CHILDREN``), and wall.
Writes ``bench/results/compile_cache.json`` with a provenance header and the load average at start and end.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def cpu_s() -> float:
    """CPU seconds of this process and its finished children (inductor's compile workers)."""
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def child(args) -> dict:
    import torch

    sys.path.insert(0, str(HERE))
    from profile_models import setup

    from omnirecon.models.fast import FAST

    torch.set_num_threads(1)
    model, src, _, _, _ = setup(args.preset)
    from omnirecon.cameras import Cameras

    w, h = args.size
    cams = src.cameras
    f = torch.full((1,), 1.2 * max(w, h))
    target = Cameras(f, f, f * 0 + w / 2, f * 0 + h / 2, cams.c2w[:1], w, h)
    model.eval()
    cpu, wall = [], []
    for _ in range(args.renders):
        c0, t0 = cpu_s(), time.perf_counter()
        with torch.no_grad():
            feats = model.encode(src)
        rgb = model.render_view(feats, target, chunk=4096)["rgb"]
        cpu.append(cpu_s() - c0)
        wall.append(time.perf_counter() - t0)
    return {"compile": FAST.compile, "first_cpu_s": round(cpu[0], 2), "first_wall_s": round(wall[0], 2),
            "steady_cpu_s": round(min(cpu[1:]), 3), "steady_wall_s": round(min(wall[1:]), 3),
            "cpu_s_all": [round(x, 3) for x in cpu], "checksum": float(rgb.double().sum())}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="ibrnet-tiny")
    parser.add_argument("--size", type=int, nargs=2, default=[64, 64], metavar=("W", "H"))
    parser.add_argument("--renders", type=int, default=3)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "compile_cache.json")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        res = child(args)
        print(json.dumps(res))
        return res
    from omnirecon.data.io import write_json
    from omnirecon.provenance import provenance

    load_start = [round(x, 2) for x in os.getloadavg()]
    cache = tempfile.mkdtemp(prefix="omnirecon_inductor_")
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", TORCHINDUCTOR_COMPILE_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(HERE.parent), os.environ.get("PYTHONPATH", "")]))
    env.pop("OMNIRECON_FAST", None)
    runs = []
    for side, fast in (("eager", ""), ("cold", "compile=1"), ("warm", "compile=1"), ("eager", "")):
        e = dict(env, OMNIRECON_FAST=fast, TORCHINDUCTOR_CACHE_DIR=cache) if fast else env
        res = subprocess.run([sys.executable, __file__, "--child", "--preset", args.preset, "--size",
                              *map(str, args.size), "--renders", str(args.renders)],
                             env=e, capture_output=True, text=True)
        if res.returncode:
            raise SystemExit(f"{side} failed:\n{res.stderr[-3000:]}")
        runs.append({"side": side} | json.loads(res.stdout.strip().splitlines()[-1]))
        print(runs[-1], flush=True)
    eager = min(r["steady_cpu_s"] for r in runs if r["side"] == "eager")
    by = {r["side"]: r for r in runs if r["side"] != "eager"}
    summary = {"eager_steady_cpu_s": eager,
               "cold_first_cpu_s": by["cold"]["first_cpu_s"], "warm_first_cpu_s": by["warm"]["first_cpu_s"],
               "compiled_steady_cpu_s": min(by["cold"]["steady_cpu_s"], by["warm"]["steady_cpu_s"]),
               "cold_overhead_cpu_s": round(by["cold"]["first_cpu_s"] - eager, 2),
               "warm_overhead_cpu_s": round(by["warm"]["first_cpu_s"] - eager, 2)}
    summary["steady_speedup"] = round(eager / summary["compiled_steady_cpu_s"], 2)
    saving = eager - summary["compiled_steady_cpu_s"]
    summary["renders_to_repay_warm"] = round(summary["warm_overhead_cpu_s"] / saving, 1) if saving > 0 else None
    summary["renders_to_repay_cold"] = round(summary["cold_overhead_cpu_s"] / saving, 1) if saving > 0 else None
    result = {"provenance": provenance(seed=0, threads=1), "preset": args.preset, "size": args.size,
              "renders": args.renders, "summary": summary, "runs": runs, "loadavg_start": load_start,
              "loadavg_end": [round(x, 2) for x in os.getloadavg()]}
    import shutil

    shutil.rmtree(cache, ignore_errors=True)
    write_json(args.out, result)
    print(json.dumps(summary, indent=1))
    return result


if __name__ == "__main__":
    main()
