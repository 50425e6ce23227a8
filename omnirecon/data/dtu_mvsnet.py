"""DTU in the MVSNet layouts: per-view ``*_cam.txt`` files and an optional ``pair.txt``.

Two layouts are read:

* test layout (MVSNet's ``dtu`` test set): ``cams/00000000_cam.txt``, ``images/00000000.jpg|png``,
  ``pair.txt``;
* training layout (``dtu_training``): ``Cameras/00000000_cam.txt`` (+ ``Cameras/pair.txt``) and
  ``Rectified/<scan>/rect_001_3_r5000.png`` (view id + 1, lighting 3 preferred, else the lowest).
  The folder may be the root (with exactly one scan under ``Rectified/``) or ``Rectified/<scan>``.

A cam file holds ``extrinsic`` (4x4 world-to-camera, OpenCV), ``intrinsic`` (3x3, pixels) and a
line ``depth_min depth_interval [num [depth_max]]``: ``near = depth_min``, ``far = depth_max`` or
``depth_min + depth_interval * (num - 1)`` (``num`` defaults to 192). The image size comes from the
images (the cam files do not store it); a principal point outside the image is refused because it
means the cams belong to another resolution. K is used as stored (pixel centres at +0.5).

The scene frame is the input frame (DTU millimetres). ``bounds`` is the box seen by at least 90% of
the views within their depth range. Splits: ``all`` and ``train = all``. ``pair.txt`` becomes
``meta["pairs"] = {str(ref_id): [source ids, best first]}``; ``meta["view_ids"]`` lists the id of
every view in file order.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from omnirecon.cameras import Cameras, nearest_views, rigid_inverse
from omnirecon.data._common import (
    assemble,
    common_size,
    detect_rig,
    dtu_splits,
    frustum_box,
    rigid_poses,
)
from omnirecon.data.io import write_image
from omnirecon.data.scene import Scene
from omnirecon.errors import InputError

NAME = "dtu_mvsnet"
DEFAULT_NUM_DEPTH = 192


def _has_cams(folder: Path) -> bool:
    return folder.is_dir() and next(folder.glob("*_cam.txt"), None) is not None


def detect(path: Path) -> bool:
    path = Path(path)
    return (_has_cams(path / "cams") or _has_cams(path / "Cameras")
            or (path.parent.name == "Rectified" and _has_cams(path.parent.parent / "Cameras")))


def _layout(path: Path) -> tuple[Path, object, list[Path]]:
    """``(cam folder, image path for a view id, candidate pair files)``."""
    if _has_cams(path / "cams"):
        def image(i):
            stem = path / "images" / f"{i:08d}"
            return next((p for p in (stem.with_suffix(".jpg"), stem.with_suffix(".png")) if p.is_file()),
                        stem.with_suffix(".jpg"))
        return path / "cams", image, [path / "pair.txt", path / "cams" / "pair.txt"]
    if path.parent.name == "Rectified" and not _has_cams(path / "Cameras"):
        root, scan = path.parent.parent, path
    else:
        root = path
        rect = path / "Rectified"
        scans = sorted(d for d in rect.iterdir() if d.is_dir()) if rect.is_dir() else []
        if len(scans) != 1:
            raise InputError(f"expected one scan folder under Rectified/, found {len(scans)}", rect,
                             "pass the scan folder itself, e.g. Rectified/scan24")
        scan = scans[0]

    def image(i):
        pref = scan / f"rect_{i + 1:03d}_3_r5000.png"
        if pref.is_file():
            return pref
        return next(iter(sorted(scan.glob(f"rect_{i + 1:03d}_*"))), pref)
    return root / "Cameras", image, [root / "Cameras" / "pair.txt", root / "pair.txt"]


def parse_cam(path: Path) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """``(w2c # [4, 4], K # [3, 3], depth values)`` of one MVSNet cam file."""
    try:
        tokens = path.read_text().split()
        e, k = tokens.index("extrinsic"), tokens.index("intrinsic")
        w2c = np.array(tokens[e + 1:e + 17], dtype=np.float64).reshape(4, 4)
        K = np.array(tokens[k + 1:k + 10], dtype=np.float64).reshape(3, 3)
        depth = [float(x) for x in tokens[k + 10:k + 14]]
    except (ValueError, UnicodeDecodeError, OSError) as err:
        raise InputError(f"malformed cam file ({type(err).__name__}: {err})", path,
                         "expected 'extrinsic' + 16 numbers, 'intrinsic' + 9 numbers, "
                         "then depth_min depth_interval") from err
    if len(depth) < 2:
        raise InputError("cam file lacks the 'depth_min depth_interval' line", path, "add it after the intrinsics")
    return w2c, K, depth


def parse_pairs(path: Path) -> dict[str, list[int]]:
    """``{str(ref_id): [source ids]}`` from an MVSNet ``pair.txt``."""
    try:
        tok = path.read_text().split()
        n, pos, out = int(tok[0]), 1, {}
        for _ in range(n):
            ref, m = int(tok[pos]), int(tok[pos + 1])
            out[str(ref)] = [int(tok[pos + 2 + 2 * j]) for j in range(m)]
            pos += 2 + 2 * m
    except (ValueError, IndexError, UnicodeDecodeError) as err:
        raise InputError(f"malformed pair file ({type(err).__name__})", path,
                         "expected N, then per view: ref id, count, and count (id score) pairs") from err
    return out


def read(path: Path, options) -> Scene:
    """Read the scene at ``path`` (see the module docstring)."""
    path = Path(path)
    cam_dir, image_of, pair_files = _layout(path)
    files = sorted(cam_dir.glob("*_cam.txt"), key=lambda p: p.name)
    ids = [int(m.group(1)) for p in files if (m := re.fullmatch(r"(\d+)_cam\.txt", p.name))]
    if len(ids) != len(files) or not files:
        raise InputError("cam files must be named <view id>_cam.txt", cam_dir, "e.g. 00000000_cam.txt")
    parsed = [parse_cam(f) for f in files]
    images = [image_of(i) for i in ids]
    width, height = common_size(images)
    w2c = torch.from_numpy(np.stack([p[0] for p in parsed]))
    rigid_poses(w2c, cam_dir)
    c2w = rigid_poses(rigid_inverse(w2c), cam_dir)
    K = torch.from_numpy(np.stack([p[1] for p in parsed]))
    for f, k in zip(files, K):
        if not (0 < k[0, 2] < width and 0 < k[1, 2] < height and k[0, 0] > 0 and k[1, 1] > 0):
            raise InputError(f"intrinsics (cx={k[0, 2]:.1f}, cy={k[1, 2]:.1f}) do not fit {width}x{height} images",
                             f, "use the cam files made for this image resolution")
    cameras = Cameras.from_K(K, c2w, width, height)
    near = torch.tensor([p[2][0] for p in parsed], dtype=torch.float64)
    far = torch.tensor([_far(d) for _, _, d in parsed], dtype=torch.float64)
    bad = ((near <= 0) | (far <= near)).nonzero()
    if len(bad):
        raise InputError("depth range must satisfy 0 < depth_min < depth_max", files[int(bad[0])],
                         "fix the last line (depth_min depth_interval) so both are positive")
    pair_file = next((p for p in pair_files if p.is_file()), None)
    meta = {"view_ids": ids, **({"pairs": parse_pairs(pair_file)} if pair_file else {})}
    return assemble(
        path=path, fmt=NAME, cameras=cameras, image_paths=images, near=near, far=far,
        bounds=frustum_box(cameras, near, far), splits=dtu_splits(len(ids)), options=options,
        rig=detect_rig(cameras), source=cam_dir, meta=meta,
    )


def _far(depth: list[float]) -> float:
    if len(depth) >= 4:
        return depth[3]
    num = depth[2] if len(depth) >= 3 else DEFAULT_NUM_DEPTH
    return depth[0] + depth[1] * (num - 1)


def write_mvsnet(scene, folder: Path, layout: str = "test", scan: str = "scan1", num_depth: int = DEFAULT_NUM_DEPTH,
                 num_sources: int = 10) -> Path:
    """Write ``scene`` in an MVSNet layout (``"test"``: cams/ + images/; ``"train"``: Cameras/ + Rectified/<scan>/).

    Cameras, near and far are written in the scene's input frame (``to_input``); images as PNG.
    ``pair.txt`` lists each view's ``num_sources`` nearest views by viewing angle. Returns ``folder``.
    """
    folder = Path(folder)
    cams = scene.cameras.transformed(scene.to_input)
    s = scene.scale_to_input
    near, far = scene.near.double() * s, scene.far.double() * s
    cam_dir = folder / ("cams" if layout == "test" else "Cameras")
    cam_dir.mkdir(parents=True, exist_ok=True)
    fmt = lambda rows: "\n".join(" ".join(f"{v:.17g}" for v in r) for r in rows.tolist())  # noqa: E731
    for i in range(len(scene)):
        interval = float(far[i] - near[i]) / (num_depth - 1)
        (cam_dir / f"{i:08d}_cam.txt").write_text(
            f"extrinsic\n{fmt(cams.w2c[i])}\n\nintrinsic\n{fmt(cams.K[i])}\n\n"
            f"{float(near[i]):.17g} {interval:.17g} {num_depth} {float(far[i]):.17g}\n")
        image = (folder / "images" / f"{i:08d}.png" if layout == "test"
                 else folder / "Rectified" / scan / f"rect_{i + 1:03d}_3_r5000.png")
        write_image(image, scene.images[i].numpy())
    k = min(num_sources, len(scene) - 1)
    src = nearest_views(cams, cams, k, by="angle", exclude=torch.arange(len(scene))) if k > 0 else None
    lines = [str(len(scene))]
    for i in range(len(scene)):
        ids = [] if src is None else src[i].tolist()
        lines += [str(i), " ".join([str(len(ids)), *(f"{j} {100.0 / (1 + r):.3f}" for r, j in enumerate(ids))])]
    ((folder if layout == "test" else cam_dir) / "pair.txt").write_text("\n".join(lines) + "\n")
    return folder
