"""LLFF scenes: ``poses_bounds.npy`` (N x 17) and an ``images`` / ``images_<N>`` folder.

Conventions:

* Row i is ``[3x5 matrix, row-major | near | far]``; the 3x5 is ``[R | t | hwf]``, a camera-to-world
  ``[R | t]`` with rotation columns ``[down, right, backwards]`` and ``hwf = (H, W, focal)`` of the
  full-resolution originals. OpenCV columns are ``[right, down, forward] = [c1, c0, -c2]``.
* Row i belongs to the i-th image in sorted filename order; a count mismatch is an error.
* Image folder: ``images`` counts as factor 1, ``images_<N>`` as factor N. ``ReadOptions.downscale``
  is relative to the largest images present (smallest factor b): the folder with the largest
  factor not above ``b * downscale`` is read and the rest of the downscale is done on load.
* H and W come from the images; ``fx = focal * W / hwf_W``, ``fy = focal * H / hwf_H``, principal
  point at the image centre.
* ``near``/``far`` are the bounds columns. The scene frame is the input frame (no NeRF ``bd_factor``
  rescaling, no recentring).
* ``rig``: ``"object"`` when the optical axes spread (mean of the unit forward vectors shorter
  than 0.9: 360° captures such as the NeRD scenes), else ``"forward"`` (fern: 0.99).
* ``bounds``: the box seen by at least 90% of the views within their near/far range.
* Splits: every 8th view (0, 8, ...) is ``test``, the rest ``train`` (``llffhold = 8``).
* Masks: ``masks_<N>/`` (or ``masks/``) beside the image folder, matched by file stem, binarised at 128.
"""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import torch

from omnirecon.cameras import Cameras
from omnirecon.data._common import (
    assemble,
    common_size,
    detect_rig,
    frustum_box,
    holdout_splits,
    mask_files,
    rigid_poses,
)
from omnirecon.data.io import list_images, read_npy
from omnirecon.data.scene import Scene
from omnirecon.errors import InputError

NAME = "llff"


def detect(path: Path) -> bool:
    return (Path(path) / "poses_bounds.npy").is_file()


def image_folders(path: Path) -> dict[int, Path]:
    """``{factor: folder}`` for ``images`` (1) and every ``images_<N>`` holding images."""
    out = {}
    for d in sorted(Path(path).iterdir()):
        m = re.fullmatch(r"images(?:_(\d+))?", d.name)
        if m and d.is_dir() and list_images(d):
            out[int(m.group(1) or 1)] = d
    return out


def pick_folder(folders: dict[int, Path], downscale: float) -> int:
    """Largest factor not above ``smallest factor x downscale``, so what remains is a downscale."""
    target = min(folders) * downscale
    fitting = [f for f in folders if f <= target * (1 + 1e-9)]
    return max(fitting) if fitting else min(folders)


def read(path: Path, options) -> Scene:
    """Read the scene at ``path`` (see the module docstring)."""
    path = Path(path)
    source = path / "poses_bounds.npy"
    arr = read_npy(source)
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0 or arr.dtype.kind not in "fiu":
        raise InputError(f"expected an N x 17 numeric array, got shape {'x'.join(map(str, arr.shape))}", source,
                         "each row must be a flattened 3x5 [R | t | hwf] matrix followed by near and far")
    arr = torch.from_numpy(arr.astype("float64"))
    n = arr.shape[0]
    folders = image_folders(path)
    if not folders:
        raise InputError("no images or images_<N> folder with images", path,
                         "put the images in images/ (or the downscaled ones in images_<N>/)")
    factor = pick_folder(folders, float(options.downscale))
    folder = folders[factor]
    images = list_images(folder)
    if len(images) != n:
        raise InputError(f"{n} poses in poses_bounds.npy but {len(images)} images in {folder.name}/", folder,
                         "give exactly one row per image (rows follow sorted filename order)")
    width, height = common_size(images)

    mats = arr[:, :15].reshape(n, 3, 5)
    hwf = mats[:, :, 4]  # [N, 3]
    if not torch.isfinite(arr).all():
        bad = int((~torch.isfinite(arr)).any(1).nonzero()[0])
        raise InputError(f"row {bad} contains NaN or infinite values", source, "regenerate the poses")
    if (hwf <= 0).any() or ((hwf[:, :2] - hwf[0, :2]).abs() > 0.5).any():
        raise InputError("hwf (height, width, focal) must be positive and the same size for all rows", source,
                         "regenerate poses_bounds.npy (LLFF imgs2poses) for images of one size")
    sx, sy = width / float(hwf[0, 1]), height / float(hwf[0, 0])
    if abs(sx - sy) > 0.01 * max(sx, sy):
        raise InputError(f"images are {width}x{height} but hwf says {hwf[0, 1]:.0f}x{hwf[0, 0]:.0f} (another aspect)",
                         folder, "use images of the captured aspect ratio (not rotated or cropped)")
    c2w = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2] = mats[:, :, 1], mats[:, :, 0], -mats[:, :, 2]
    c2w[:, :3, 3] = mats[:, :, 3]
    c2w = rigid_poses(c2w, source)
    focal = hwf[:, 2]
    cameras = Cameras(focal * sx, focal * sy, width / 2, height / 2, c2w, width, height)
    near, far = arr[:, 15], arr[:, 16]
    if ((near <= 0) | (far <= near)).any():
        bad = int(((near <= 0) | (far <= near)).nonzero()[0])
        raise InputError(f"row {bad} has bounds near={near[bad]:.4g}, far={far[bad]:.4g}; need 0 < near < far", source,
                         "fix that row's last two numbers (near, far), or regenerate poses_bounds.npy")

    remaining = min(folders) * float(options.downscale) / factor
    return assemble(
        path=path, fmt=NAME, cameras=cameras, image_paths=images, near=near, far=far,
        bounds=frustum_box(cameras, near, far), splits=holdout_splits(n), options=replace(options, downscale=remaining),
        rig=detect_rig(cameras), source=source, mask_paths=mask_files(path, factor, images),
        meta={"image_folder": folder.name, "hwf": hwf[0].tolist()},
    )

