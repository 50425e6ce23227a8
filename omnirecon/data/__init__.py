"""Dataset readers. ``load_scene(path)`` detects the format and returns a :class:`Scene`.

Each reader module defines ``NAME``, ``detect(path) -> bool`` and ``read(path, options) -> Scene``.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from omnirecon.data.scene import Scene
from omnirecon.errors import InputError

# Detection order matters: the more specific layouts come first.
READERS = {
    "blender": "omnirecon.data.blender",
    "ngp": "omnirecon.data.ngp",
    "llff": "omnirecon.data.llff",
    "dtu_neus": "omnirecon.data.dtu_neus",
    "dtu_mvsnet": "omnirecon.data.dtu_mvsnet",
    "colmap": "omnirecon.data.colmap",
}
Format = Literal["auto", "blender", "ngp", "llff", "dtu_neus", "dtu_mvsnet", "colmap"]


@dataclass
class ReadOptions:
    """Options every reader accepts."""

    downscale: float = 1.0
    """Divide the image resolution by this factor on load (intrinsics follow)."""
    background: Literal["white", "black"] = "white"
    """Colour that RGBA images are composited on."""
    splits: tuple[str, ...] | None = None
    """Load only the views of these splits (e.g. ``("train",)``); ``None`` loads all."""
    max_views: int | None = None
    """Keep at most this many views (evenly spaced), to bound memory on large captures."""


def detect_format(path: Path) -> str:
    """Name of the reader that recognises ``path``; :class:`InputError` if none does."""
    path = Path(path)
    if not path.exists():
        raise InputError("path does not exist", path, "pass a scene folder")
    if not path.is_dir():
        raise InputError("expected a scene folder, got a file", path, "pass the folder that holds the scene")
    for name, module in READERS.items():
        if importlib.import_module(module).detect(path):
            return name
    raise InputError(
        "no supported scene format found (looked for transforms*.json, poses_bounds.npy, cameras_sphere.npz, "
        "Cameras/*_cam.txt, sparse/ or cameras.txt/.bin)", path,
        "point at the scene folder, or force a reader with --format")


def load_scene(path: str | Path, format: Format = "auto", options: ReadOptions | None = None) -> Scene:
    """Read the scene at ``path`` with the named reader (``"auto"`` detects it)."""
    path = Path(path)
    options = options or ReadOptions()
    if format == "auto":
        format = detect_format(path)
    elif format not in READERS:
        raise InputError(f"unknown format {format!r}", None, f"use one of {', '.join(READERS)}")
    if not path.is_dir():
        raise InputError("scene folder does not exist" if not path.exists() else "expected a scene folder", path,
                         "pass the folder that holds the scene")
    from omnirecon.preflight import check_format  # a forced --format that does not fit the folder: one line

    check_format(path, format, READERS)
    scene = importlib.import_module(READERS[format]).read(path, options)
    scene.validate()
    return scene
