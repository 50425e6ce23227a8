"""instant-ngp / nerfstudio scenes: one ``transforms.json`` with pixel intrinsics.

Conventions:

* ``frames[i].transform_matrix``: camera-to-world, OpenGL camera frame; converted to OpenCV. The
  scene frame is the json's frame. nerfstudio's ``applied_transform`` records how the poses were
  already moved, so it is ignored.
* Intrinsics ``fl_x, fl_y, cx, cy, w, h`` at the top level or per frame (``camera_angle_x/y`` as
  fallback). Non-zero ``k1, k2, k3, k4, p1, p2`` (OpenCV radial-tangential, normalised coordinates)
  are removed on load: images and masks are resampled onto the pinhole camera with the same K.
  Fisheye and other non-pinhole ``camera_model`` values are refused.
* ``rig`` from the spread of the optical axes (see ``_common.detect_rig``; the fox is ``"object"``).
* Splits: every 8th frame (0, 8, ...) is ``test``, the rest ``train`` (the LLFF ``llffhold`` rule).
* ``bounds``: instant-ngp models the cube ``[0.5 - aabb_scale/2, 0.5 + aabb_scale/2]^3`` of its own
  space ``x_ngp = scale * x + offset`` (defaults ``scale = 0.33``, ``offset = 0.5``); inside that cube
  the content box is the part seen by at least 90% of the views. ``near`` is the content box's
  nearest corner depth, ``far`` the farthest corner depth of the whole ngp cube (the background
  instant-ngp would render).
* nerfstudio's per-frame ``mask_path`` marks pixels to ignore (not an object silhouette) and is
  not read.
"""

from __future__ import annotations

from pathlib import Path

import torch

from omnirecon.data._common import (
    assemble,
    common_size,
    detect_rig,
    frustum_box,
    holdout_splits,
    near_far_from_box,
)
from omnirecon.data._transforms import Frames, _num
from omnirecon.data.io import read_json
from omnirecon.data.scene import Scene
from omnirecon.errors import InputError

NAME = "ngp"
CLAIM_KEYS = (b'"fl_x"', b'"fl_y"', b'"camera_model"', b'"aabb_scale"', b'"k1"')


def detect(path: Path) -> bool:
    """``transforms.json`` with pixel intrinsics or instant-ngp keys (and no Blender split files)."""
    f = Path(path) / "transforms.json"
    if not f.is_file() or (Path(path) / "transforms_train.json").is_file():
        return False
    with open(f, "rb") as fh:
        head = fh.read(1 << 16)
    return any(k in head for k in CLAIM_KEYS)


def ngp_cube(meta: dict, source: Path) -> torch.Tensor:
    """instant-ngp's modelled cube, in the json's frame. ``# [2, 3]``"""
    a = _num(meta.get("aabb_scale", 1), source, "aabb_scale")
    scale = _num(meta.get("scale", 0.33), source, "scale")
    offset = meta.get("offset", [0.5, 0.5, 0.5])
    if not isinstance(offset, list) or len(offset) != 3:
        raise InputError("offset must be a list of 3 numbers", source,
                         "give offset as [x, y, z], or leave it out for [0.5, 0.5, 0.5]")
    off = torch.tensor([_num(o, source, "offset") for o in offset], dtype=torch.float64)
    if a <= 0 or scale <= 0:
        raise InputError("aabb_scale and scale must be positive", source,
                         "give positive numbers, or leave them out for 1 and 0.33")
    return torch.stack([(0.5 - a / 2 - off) / scale, (0.5 + a / 2 - off) / scale])


def read(path: Path, options) -> Scene:
    """Read the scene at ``path`` (see the module docstring)."""
    path = Path(path)
    source = path / "transforms.json"
    meta = read_json(source)
    frames = Frames(path)
    frames.add(meta, source)
    width, height = common_size(frames.images, *frames.declared_size())
    cameras, dist = frames.cameras(width, height)

    cube = ngp_cube(meta, source)
    near0, far0 = near_far_from_box(cameras, cube)
    bounds = frustum_box(cameras, near0, far0, region=cube)
    near = near_far_from_box(cameras, bounds.double())[0]
    far = torch.maximum(far0, near * 1.01)
    return assemble(
        path=path, fmt=NAME, cameras=cameras, image_paths=frames.images, near=near, far=far, bounds=bounds,
        splits=holdout_splits(len(cameras)), options=options, rig=detect_rig(cameras), source=source,
        distortion=dist,
        meta={"aabb_scale": meta.get("aabb_scale", 1), "ngp_cube": cube.tolist()},
    )
