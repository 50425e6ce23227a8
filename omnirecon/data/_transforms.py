"""Parsing shared by the two ``transforms*.json`` readers (Blender/NeRF-synthetic and instant-ngp).

Both store OpenGL camera-to-world ``transform_matrix`` per frame and the same intrinsic keys, at
the top level or per frame: ``fl_x, fl_y, cx, cy, w, h`` (pixels), else ``camera_angle_x/y``
(radians), plus optional distortion ``k1, k2, k3, k4, p1, p2`` and ``camera_model``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from omnirecon.cameras import Cameras, opengl_to_opencv
from omnirecon.data._common import pose_matrix, resolve_image, rigid_poses
from omnirecon.errors import InputError

INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
                  "k1", "k2", "k3", "k4", "p1", "p2", "camera_model", "is_fisheye")
DIST_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
PINHOLE_MODELS = {None, "PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL", "PERSPECTIVE"}


class Frames:
    """All frames of one or more transforms files, in file order.

    Attributes: ``images`` (paths), ``c2w_gl`` (list of 4x4 numpy), ``fields`` (intrinsic keys per
    frame, frame values overriding the file's top level), ``frames`` (the raw frame dicts),
    ``sources`` (the json file of each frame).
    """

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.images: list[Path] = []
        self.c2w_gl: list = []
        self.fields: list[dict] = []
        self.frames: list[dict] = []
        self.sources: list[Path] = []

    def add(self, meta: dict, source: Path) -> list[int]:
        """Append the frames of one parsed json file; returns their indices."""
        frames = meta.get("frames") if isinstance(meta, dict) else None
        if not isinstance(frames, list) or not frames:
            raise InputError("no frames: expected a non-empty list under \"frames\"", source,
                             "give one entry per image with file_path and transform_matrix")
        start = len(self.images)
        for i, fr in enumerate(frames):
            if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
                raise InputError(f"frame {i} lacks file_path or transform_matrix", source,
                                 "give both keys in every frame")
            self.images.append(resolve_image(self.folder, fr["file_path"], source))
            self.c2w_gl.append(pose_matrix(fr["transform_matrix"], source, f"frame {i} transform_matrix"))
            self.fields.append({k: fr.get(k, meta.get(k)) for k in INTRINSIC_KEYS})
            self.frames.append(fr)
            self.sources.append(source)
        # check per file so that the message names the right json
        rigid_poses(opengl_to_opencv(torch.from_numpy(np.stack(self.c2w_gl[start:]))), source)
        return list(range(start, len(self.images)))

    def declared_size(self) -> tuple[tuple[int, int] | None, str]:
        """``(w, h)`` from the json (first frame that declares it) and a phrase naming its file."""
        for f, src in zip(self.fields, self.sources):
            if f["w"] is not None and f["h"] is not None:
                w, h = int(round(_num(f["w"], src, "w"))), int(round(_num(f["h"], src, "h")))
                if not (0 < w <= 100_000 and 0 < h <= 100_000):
                    raise InputError(f"image size w={w}, h={h} is not a plausible size in pixels", src,
                                     "give the images' width and height in pixels, or remove w and h")
                return (w, h), f"{src.name} gives"
        return None, ""

    def cameras(self, width: int, height: int) -> tuple[Cameras, torch.Tensor]:
        """OpenCV cameras for all frames at ``width x height`` and distortion ``# [N, 6]``."""
        c2w = rigid_poses(opengl_to_opencv(torch.from_numpy(np.stack(self.c2w_gl))), self.sources[0])
        K = torch.tensor([intrinsics(f, width, height, s) for f, s in zip(self.fields, self.sources)],
                         dtype=torch.float64)  # [N, 10]
        return Cameras(K[:, 0], K[:, 1], K[:, 2], K[:, 3], c2w, width, height), K[:, 4:]


def _num(value, source: Path, key: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as e:
        raise InputError(f"{key} is not a number ({str(value)[:40]!r})", source, f"give {key} as a number") from e
    if not math.isfinite(v):
        raise InputError(f"{key} is not finite", source, f"give {key} as a finite number")
    return v


def intrinsics(f: dict, width: int, height: int, source: Path) -> list[float]:
    """``[fx, fy, cx, cy, k1, k2, k3, k4, p1, p2]`` of one frame's fields."""
    model = f["camera_model"]
    if f["is_fisheye"] or (model is not None and str(model).upper() not in PINHOLE_MODELS):
        raise InputError(f"unsupported camera model {model or 'fisheye'!s}", source,
                         "undistort the images to a pinhole/OPENCV model first (e.g. colmap image_undistorter)")
    get = lambda k: None if f[k] is None else _num(f[k], source, k)  # noqa: E731
    for key in ("camera_angle_x", "camera_angle_y"):
        if f[key] is not None and not 0 < get(key) < math.pi:
            raise InputError(f"{key} is {f[key]}, outside (0, pi) radians", source,
                             "give the horizontal field of view in radians (e.g. 0.69), or fl_x in pixels")
    fx, fy = get("fl_x"), get("fl_y")
    if fx is None and f["camera_angle_x"] is not None:
        fx = 0.5 * width / math.tan(0.5 * get("camera_angle_x"))
    if fy is None and f["camera_angle_y"] is not None:
        fy = 0.5 * height / math.tan(0.5 * get("camera_angle_y"))
    fx, fy = fx if fx is not None else fy, fy if fy is not None else fx
    if fx is None:
        raise InputError("no focal length (fl_x/fl_y or camera_angle_x)", source,
                         "add fl_x (pixels) or camera_angle_x (radians)")
    if not (math.isfinite(fx) and math.isfinite(fy) and fx > 0 and fy > 0):
        raise InputError(f"focal length fl_x={fx:g}, fl_y={fy:g} is not positive", source,
                         "give positive fl_x/fl_y in pixels (or camera_angle_x in radians)")
    cx, cy = get("cx"), get("cy")
    dist = [get(k) or 0.0 for k in DIST_KEYS]
    return [fx, fy, width / 2 if cx is None else cx, height / 2 if cy is None else cy, *dist]
