"""Blender / NeRF-synthetic scenes: ``transforms_{train,val,test}.json`` (or one ``transforms.json``).

Layout and conventions:

* ``frames[i].transform_matrix``: camera-to-world, OpenGL camera frame; converted to OpenCV.
* ``camera_angle_x`` (radians): ``fx = fy = 0.5 W / tan(0.5 camera_angle_x)``, principal point at
  the image centre. ``file_path`` may omit the extension (``.png`` is appended).
* RGBA images are composited on ``ReadOptions.background``; ``mask = alpha > 0.5``.
* Splits are the json files (``train``, ``val``, ``test``); a single ``transforms.json`` gives only
  ``all``. The scene frame is the input frame; ``near = 2``, ``far = 6``, ``bounds = [-1.5, 1.5]^3``
  (the NeRF defaults), ``rig = "object"``.
* The upstream ``test/r_*_depth_*.png`` files are 8-bit visualisations and are not read.

Extension written by ``omnirecon synth`` (all optional). Top level: ``fl_x, fl_y, cx, cy, w, h``
(pixels, override ``camera_angle_x``), ``near``, ``far`` (scalars), ``aabb`` (``[[min], [max]]``),
``rig``, ``background`` (``[r, g, b]`` in 0..1, the colour of RGB renders), ``mesh_path`` (exact
ground-truth PLY in the scene frame), ``depth_scale``. Per frame, paths relative to the folder:

* ``depth_file_path``: 16-bit PNG, z-depth = value x depth_scale, 0 = no surface;
* ``normal_file_path``: 8-bit RGB, world normal ``2 v / 255 - 1``; a decoded length outside
  0.5..1.5 (e.g. ``0,0,0`` or ``128,128,128``) means no surface and reads as 0;
* ``label_file_path``: 8/16-bit object ids, 0 = background;
* ``mask_file_path``: 8-bit, > 127 = foreground; used instead of alpha when every frame has one.

Depth, normal and label maps are resampled with nearest neighbour (the source pixel holding the
new pixel's centre), colour and masks with area averaging.
"""

from __future__ import annotations

from pathlib import Path

import torch

from omnirecon.data import ngp
from omnirecon.data._common import assemble, common_size
from omnirecon.data._transforms import Frames, _num
from omnirecon.data.io import read_json
from omnirecon.data.scene import Scene
from omnirecon.errors import InputError

NAME = "blender"
SPLITS = ("train", "val", "test")
DEFAULT_NEAR, DEFAULT_FAR, DEFAULT_HALF_SIZE = 2.0, 6.0, 1.5


def detect(path: Path) -> bool:
    """``transforms_train.json`` present, or a ``transforms.json`` that instant-ngp does not claim."""
    path = Path(path)
    if (path / "transforms_train.json").is_file():
        return True
    return (path / "transforms.json").is_file() and not ngp.detect(path)


def read(path: Path, options) -> Scene:
    """Read the scene at ``path`` (see the module docstring)."""
    path = Path(path)
    files = [(s, path / f"transforms_{s}.json") for s in SPLITS if (path / f"transforms_{s}.json").is_file()]
    if not files:
        if not (path / "transforms.json").is_file():
            raise InputError("no transforms_train.json or transforms.json", path, "point at a Blender scene folder")
        files = [("all", path / "transforms.json")]
    frames, splits, top = Frames(path), {}, {}
    for split, file in files:
        meta = read_json(file)
        idx = frames.add(meta, file)
        if split != "all":
            splits[split] = idx
        for k, v in meta.items():
            if k != "frames":
                top.setdefault(k, (v, file))
    source = files[0][1]
    width, height = common_size(frames.images, *frames.declared_size())
    cameras, dist = frames.cameras(width, height)
    n = len(cameras)

    def scalar(key, default):
        return default if key not in top else _num(top[key][0], top[key][1], key)

    near = torch.full((n,), scalar("near", DEFAULT_NEAR), dtype=torch.float64)
    far = torch.full((n,), scalar("far", DEFAULT_FAR), dtype=torch.float64)
    bounds = torch.tensor([[-DEFAULT_HALF_SIZE] * 3, [DEFAULT_HALF_SIZE] * 3])
    if "aabb" in top:
        bounds = _floats(*top["aabb"], "aabb", (2, 3))
        if (bounds[1] <= bounds[0]).any():
            raise InputError("aabb max must exceed min on every axis", top["aabb"][1],
                             "give aabb as [[min x, y, z], [max x, y, z]]")
    rig = str(top.get("rig", ("object",))[0])
    if rig not in ("object", "forward"):
        raise InputError(f"rig must be \"object\" or \"forward\", got {rig!r}", top["rig"][1],
                         "set \"rig\" to object or forward")
    background = None
    if "background" in top:
        background = tuple(_floats(*top["background"], "background", (3,)).tolist())
    mesh_path = None
    if "mesh_path" in top:
        mesh_path = path / str(top["mesh_path"][0])
        if not mesh_path.is_file():
            raise InputError("mesh file named by mesh_path is missing", mesh_path, "fix mesh_path in the json")

    def per_frame(key):
        paths = [path / str(f[key]) if f.get(key) else None for f in frames.frames]
        return paths if any(p is not None for p in paths) else None

    masks = per_frame("mask_file_path")
    return assemble(
        path=path, fmt=NAME, cameras=cameras, image_paths=frames.images, near=near, far=far, bounds=bounds,
        splits=splits, options=options, rig=rig, source=source, distortion=dist,
        mask_paths=masks if masks is not None and all(p is not None for p in masks) else None,
        depth_paths=per_frame("depth_file_path"), depth_scale=scalar("depth_scale", 1.0),
        normal_paths=per_frame("normal_file_path"), label_paths=per_frame("label_file_path"),
        background=background, mesh_path=mesh_path,
    )


def _floats(value, source: Path, key: str, shape: tuple[int, ...]) -> torch.Tensor:
    try:
        t = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{key} is not a list of numbers", source, f"give {key} as a list of numbers") from e
    if tuple(t.shape) != shape or not torch.isfinite(t).all():
        raise InputError(f"{key} must hold {'x'.join(map(str, shape))} finite numbers, got {str(value)[:60]}", source,
                         f"give {key} as {'x'.join(map(str, shape))} finite numbers")
    return t
