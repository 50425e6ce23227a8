"""Provenance header for every published number: commit, versions, device, seed."""

from __future__ import annotations

import os
import platform
import subprocess
import time
from pathlib import Path

RESULTS = ("bench/results", "BENCHMARKS.md")
"""What benchmarks write: changes there do not make the code that produces a number ``+dirty`` (a bench run that
writes its results file as each row finishes stamped its later rows ``+dirty``)."""


def git_commit(root: Path | None = None) -> str:
    """The checkout's commit, ``+dirty`` when a tracked file other than the benchmarks' results (:data:`RESULTS`)
    differs from it."""
    root = root or Path(__file__).resolve().parents[1]
    try:
        sha = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=root, capture_output=True,
                             text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                                *(f":(exclude){p}" for p in RESULTS)], cwd=root,
                               capture_output=True, text=True).stdout.strip()
        return sha + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def provenance(seed: int | None = None, **extra) -> dict:
    """A JSON-serialisable record of what produced a result."""
    import numpy
    import torch

    import omnirecon

    device = "cpu"
    if torch.cuda.is_available():
        device = f"cuda: {torch.cuda.get_device_name(0)}"
    return {
        "commit": git_commit(),
        "omnirecon": omnirecon.__version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": numpy.__version__,
        "device": device,
        "cpu": cpu_name(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),  # AVX2 / AVX512: the same "AMD EPYC" name has
        # been both, and CPU seconds compare only within one (bf16 autocast runs emulated, far slower, on AVX2)
        "cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "seed": seed,
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "loadavg_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
        **extra,
    }


def markdown_header(prov: dict) -> str:
    """One line for a Markdown page."""
    keys = ("commit", "omnirecon", "python", "torch", "numpy", "device", "cpu", "cpu_capability", "cores", "seed", "date",
            "loadavg_1min")
    return "Provenance: " + "; ".join(f"{k} `{prov.get(k)}`" for k in keys if k in prov)
