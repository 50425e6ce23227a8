"""``omnirecon doctor``: what works on this machine, what falls back, and how to fix it.

Every check really runs the thing it names (a CUDA tensor op, an EGL context in a subprocess, the
Chromium binary, an import), with a timeout; nothing is downloaded. Rows have a status:

* ``ok``: works;
* ``fallback``: missing, and a slower or reduced path is used instead (the row says which);
* ``missing``: missing, and the feature that needs it is unavailable (the row says how to get it).
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from omnirecon import metrics
from omnirecon.engine.checkpoint import SIZES_FOLDER
from omnirecon.engine.shipped import shipped_folder
from omnirecon.viewer.bundle import find_three, three_unavailable_reason

ROOT = Path(__file__).resolve().parents[2]
"""The source checkout the package runs from (its neighbour ``../shared/data`` holds the evaluation scenes)."""

EGL_PROBE = ("import moderngl; c = moderngl.create_standalone_context(backend='egl'); "
             "print(c.info['GL_RENDERER'], '|', c.info['GL_VERSION'])")


@dataclass
class Check:
    """One row of the doctor's table."""

    name: str
    """What is checked."""
    status: str
    """``ok``, ``fallback`` or ``missing``."""
    detail: str
    """Version, device or the error seen."""
    consequence: str = ""
    """What happens without it, and the fix."""


def _run(cmd: list[str], timeout: float = 30.0) -> tuple[int, str]:
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        text = (p.stdout.strip() or p.stderr.strip()).splitlines()
        return p.returncode, (text[-1] if text else "")
    except (OSError, subprocess.TimeoutExpired) as e:
        return 1, f"{type(e).__name__}: {e}"


def check_torch() -> list[Check]:
    import torch

    rows = [Check("torch", "ok", f"{torch.__version__}, {torch.get_num_threads()} CPU threads")]
    if torch.cuda.is_available():
        try:
            x = torch.ones(8, device="cuda")
            name = torch.cuda.get_device_name(0)
            rows.append(Check("CUDA", "ok", f"{name}, CUDA {torch.version.cuda}, sum test {float(x.sum()):.0f}"))
        except RuntimeError as e:  # a driver/toolkit mismatch shows up here, not in is_available()
            rows.append(Check("CUDA", "fallback", str(e).splitlines()[0], "everything runs on the CPU"))
    else:
        why = "CPU-only torch build" if torch.version.cuda is None else "no CUDA device visible"
        rows.append(Check("CUDA", "fallback", why, "training and rendering run on the CPU (tiny presets)"))
    try:
        import torch.distributed as dist

        rows.append(Check("torch.distributed (gloo)", "ok" if dist.is_gloo_available() else "missing",
                          "gloo" + (", nccl" if dist.is_nccl_available() else ""),
                          "" if dist.is_gloo_available() else "torchrun DDP on the CPU is unavailable"))
    except ImportError as e:
        rows.append(Check("torch.distributed", "missing", str(e), "no DDP"))
    return rows


def check_egl() -> Check:
    if importlib.util.find_spec("moderngl") is None:
        return Check("EGL rasterization (moderngl)", "fallback", "moderngl not installed",
                     "meshes are rasterized by the NumPy reference (slow); `pip install -e .[raster]`")
    code, out = _run([sys.executable, "-c", EGL_PROBE])
    if code == 0:
        return Check("EGL rasterization (moderngl)", "ok", out)
    return Check("EGL rasterization (moderngl)", "fallback", out or f"exit {code}",
                 "NumPy reference rasterizer (slow); install libegl1 libegl-mesa0 libgl1-mesa-dri "
                 "(scripts/setup_system.sh as root)")


def check_chromium() -> Check:
    exe = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)
    if exe is None:
        return Check("Chromium (browser tests)", "missing", "no chromium on PATH",
                     "the web-viewer screenshot test skips; apt-get install chromium")
    code, out = _run([exe, "--headless", "--no-sandbox", "--version"])
    return Check("Chromium (browser tests)", "ok" if code == 0 else "missing", out or exe,
                 "" if code == 0 else "the browser cannot start; the web-viewer test skips")


def check_three() -> Check:

    three = find_three()
    if three is None:
        return Check("three.js (web viewer)", "missing", three_unavailable_reason(),
                     "omnirecon export needs --no-viewer and the browser test skips; npm install in omnirecon/viewer")
    try:
        version = json.loads((three / "package.json").read_text()).get("version", "?")
    except (OSError, ValueError):
        version = "?"
    return Check("three.js (web viewer)", "ok", f"three {version} in {three}")


def check_module(name: str, module: str, consequence: str) -> Check:
    if importlib.util.find_spec(module) is None:
        return Check(name, "missing", f"`{module}` not importable", consequence)
    try:
        from importlib.metadata import version

        return Check(name, "ok", f"{module} {version(module.replace('_', '-'))}")
    except Exception:  # noqa: BLE001 - a module without distribution metadata still works
        return Check(name, "ok", module)


def check_metrics() -> list[Check]:

    rows = []
    for key, name, consequence in (("st_lpips", "ST-LPIPS (stlpips-pytorch)", "the st_lpips column is left out"),
                                   ("lpips", "LPIPS weights (lpips + cached AlexNet)",
                                    "the lpips column is reported as unavailable (nothing is downloaded)")):
        why = metrics.unavailable(key)
        rows.append(Check(name, "ok" if not why else "missing", why or "available", "" if not why else consequence))
    return rows


def check_video() -> Check:
    try:
        import imageio_ffmpeg

        return Check("MP4 video (imageio-ffmpeg)", "ok", imageio_ffmpeg.get_ffmpeg_exe())
    except (ImportError, RuntimeError) as e:
        return Check("MP4 video (imageio-ffmpeg)", "fallback", str(e).splitlines()[0] if str(e) else "not installed",
                     "videos are written as GIF; `pip install -e .[video]`")


def check_data() -> list[Check]:
    rows = []
    shared = ROOT.parent / "shared" / "data"
    rows.append(Check("shared evaluation scenes", "ok" if shared.is_dir() else "missing", str(shared),
                      "" if shared.is_dir() else "tests that need real scenes skip; benchmarks score procedural scenes only"))
    ckpts = sorted(p.name + "".join(f" (+{q.name} px)" for q in sorted((p / SIZES_FOLDER).glob("*"))
                                    if (q / "model.safetensors").is_file())
                   for p in shipped_folder().glob("*") if (p / "model.safetensors").is_file())
    rows.append(Check("shipped checkpoints", "ok" if ckpts else "missing", ", ".join(ckpts) or "none",
                      "" if ckpts else "train one with python -m bench train_tiny"))
    return rows


def run_checks() -> list[Check]:
    """Every check, in table order."""
    rows = check_torch()
    rows.append(check_egl())
    rows.append(check_chromium())
    rows.append(check_three())
    rows.append(check_video())
    rows += check_metrics()
    rows.append(check_module("TensorBoard event files", "tensorboard", "metrics.jsonl only; pip install tensorboard"))
    rows += check_data()
    return rows
