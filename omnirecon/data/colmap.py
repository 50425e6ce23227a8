"""COLMAP sparse reconstructions (text or binary) with their images.

Layout: the model in ``sparse/0/``, ``sparse/`` or the folder itself (``.bin`` preferred over
``.txt``); images by name in ``images/`` beside ``sparse/`` (also looked for one and two levels up
when the folder is the model itself).

Conventions:

* Poses are world-to-camera, OpenCV frame, pixel centres at +0.5 (no shift needed). Images are
  sorted by name.
* Scene frame: COLMAP's frame is arbitrary (rotation and scale come from the first image pair), so
  the scene frame is the upright, unit-scaled one of :func:`omnirecon.data.frame.upright_frame`: +z
  up (from the cameras), the robust box of the 3-D points centred at 0 with half-diagonal 1.
  ``to_input`` maps back to the model's frame, so exports land in COLMAP's coordinates.
* Images: ``images/`` holds them at the cameras' size; ``images_<N>/`` beside it (written by
  ``omnirecon process``) the same at 1/N size. ``ReadOptions.downscale`` reads the folder with the
  largest N not above it and does the rest of the downscale on load.
* Camera models: ``SIMPLE_PINHOLE``, ``PINHOLE``; ``SIMPLE_RADIAL``, ``RADIAL`` and ``OPENCV`` are
  undistorted on load (images resampled onto the pinhole camera with the same K). Others (fisheye,
  ``FULL_OPENCV``, ...) are refused: run ``colmap image_undistorter`` first. All cameras must share
  one image size, which must match the image files.
* ``near``/``far`` per view: 1st / 99th percentile of the z-depth of the 3-D points the view
  observes, times 0.9 / 1.1 (at least 8 points; else the points that project into it; else the
  median range of the other views).
* ``bounds``: per-axis 1st to 99th percentile of the 3-D points in the scene frame, padded by 5%
  of the extent. Only points two registered cameras see at least 1.5 degrees apart count here and for ``near``/``far``
  (:func:`triangulated`): a point seen from one direction only (the far end of a street walked along) has no
  reliable depth and would stretch the box toward infinity.
* Masks: ``masks/`` (``masks_<N>/`` with ``images_<N>/``) beside ``images/``, one per image matched by stem
  (``IMG_1.png`` or ``IMG_1.jpg.png``), > 127 = object: the scene's object masks (``omnirecon process --masks``
  writes them, undistorted like the photos).
* ``rig`` from the spread of the optical axes; splits: every 8th view is ``test`` (``llffhold``).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from omnirecon.cameras import Cameras, rigid_inverse
from omnirecon.data._common import assemble, common_size, detect_rig, holdout_splits, inside, mask_files, rigid_poses
from omnirecon.data.colmap_io import find_model, qvec_to_rotmat, read_model
from omnirecon.data.frame import upright_frame
from omnirecon.data.scene import Scene
from omnirecon.errors import InputError

NAME = "colmap"
MIN_POINTS = 8
MIN_TRIANGULATION_DEGREES = 1.5
"""Points seen from directions less far apart than this bound neither the scene nor its depth ranges (COLMAP's own
filter uses the same angle)."""


def detect(path: Path) -> bool:
    return find_model(Path(path)) is not None


def pinhole_params(model: str, p: np.ndarray, source: Path) -> tuple[list[float], list[float]]:
    """``([fx, fy, cx, cy], [k1, k2, k3, k4, p1, p2])`` of a supported COLMAP camera model."""
    if model == "SIMPLE_PINHOLE":
        return [p[0], p[0], p[1], p[2]], [0.0] * 6
    if model == "PINHOLE":
        return list(p[:4]), [0.0] * 6
    if model == "SIMPLE_RADIAL":
        return [p[0], p[0], p[1], p[2]], [p[3], 0, 0, 0, 0, 0]
    if model == "RADIAL":
        return [p[0], p[0], p[1], p[2]], [p[3], p[4], 0, 0, 0, 0]
    if model == "OPENCV":
        return list(p[:4]), [p[4], p[5], 0, 0, p[6], p[7]]
    raise InputError(f"unsupported camera model {model}", source,
                     "run 'colmap image_undistorter' and read its output (PINHOLE cameras)")


def read(path: Path, options) -> Scene:
    """Read the scene at ``path`` (see the module docstring)."""
    path = Path(path)
    found = find_model(path)
    if found is None:
        raise InputError("no COLMAP model (cameras/images .bin or .txt) in sparse/0, sparse or here", path,
                         "point at the folder that holds sparse/ and images/")
    model = read_model(*found)
    cam_file = model.folder / f"cameras{model.ext}"
    img_file = model.folder / f"images{model.ext}"
    if not model.images:
        raise InputError("the model has no images", img_file, "reconstruct (or register) some images first")
    images = sorted(model.images, key=lambda im: im.name)
    missing = sorted({im.camera_id for im in images} - set(model.cameras))
    if missing:
        raise InputError(f"images refer to camera {missing[0]}, which is not in the model", cam_file,
                         "re-export the model so that every image's camera id is listed in the cameras file")
    sizes = {(model.cameras[im.camera_id].width, model.cameras[im.camera_id].height) for im in images}
    if len(sizes) != 1:
        raise InputError(f"cameras have different image sizes {sorted(sizes)}", cam_file,
                         "undistort/resize all images to one size (colmap image_undistorter)")
    width, height = sizes.pop()
    intr = [pinhole_params(model.cameras[im.camera_id].model, model.cameras[im.camera_id].params, cam_file)
            for im in images]
    K = torch.tensor([i[0] for i in intr], dtype=torch.float64)  # [N, 4]
    dist = torch.tensor([i[1] for i in intr], dtype=torch.float64)  # [N, 6]

    w2c = torch.eye(4, dtype=torch.float64).repeat(len(images), 1, 1)
    for i, im in enumerate(images):
        if not (np.isfinite(im.qvec).all() and np.isfinite(im.tvec).all()) or np.linalg.norm(im.qvec) < 1e-12:
            raise InputError(f"image {im.name} has a non-finite or zero pose", img_file, "re-run the reconstruction")
        w2c[i, :3, :3] = torch.from_numpy(qvec_to_rotmat(im.qvec))
        w2c[i, :3, 3] = torch.from_numpy(im.tvec)
    c2w = rigid_poses(rigid_inverse(w2c), img_file)

    pts_file = model.folder / f"points3D{model.ext}"
    if model.points.xyz.shape[0] < MIN_POINTS:
        raise InputError(f"only {model.points.xyz.shape[0]} 3-D points: cannot derive depth bounds", pts_file,
                         "triangulate the model (colmap point_triangulator) before reading it")
    steady = triangulated(model.points.tracks, {im.id: c for im, c in zip(images, c2w[:, :3, 3].numpy())},
                          model.points.xyz)  # [P]: points whose depth the poses pin down
    if steady.sum() < MIN_POINTS:
        steady[:] = True
    T, (lo, hi) = upright_frame(c2w.numpy(), model.points.xyz[steady])  # scene <- model frame
    T = torch.from_numpy(T)
    xyz = torch.from_numpy(model.points.xyz[steady]) @ T[:3, :3].T + T[:3, 3]  # [P', 3] in the scene frame
    cameras = Cameras(K[:, 0], K[:, 1], K[:, 2], K[:, 3], c2w, width, height).transformed(T)
    near, far = _near_far(cameras, images, model.points.ids[steady], xyz, pts_file)
    lo, hi = torch.from_numpy(lo), torch.from_numpy(hi)
    pad = 0.05 * (hi - lo).clamp_min(1e-9)
    bounds = torch.stack([lo - pad, hi + pad])

    roots = [path, path.parent, path.parent.parent]
    root = next((r for r in roots if (r / "images").is_dir()), path)
    files = [inside(root / "images", im.name, img_file) for im in images]  # names stay inside images/
    common_size(files, (width, height), f"{cam_file.name} gives")
    factor, downscale = _image_folder(root, [im.name for im in images], cameras, float(options.downscale))
    if factor > 1:
        files = [root / f"images_{factor}" / im.name for im in images]
        cameras = cameras.rescaled(1.0 / factor)
    return assemble(
        path=path, fmt=NAME, cameras=cameras, image_paths=files, near=near, far=far, bounds=bounds,
        splits=holdout_splits(len(images)), options=replace(options, downscale=downscale), rig=detect_rig(cameras),
        source=img_file, distortion=dist, to_input=torch.linalg.inv(T), mask_paths=mask_files(root, factor, files),
        meta={"model": str(model.folder.relative_to(path)) if model.folder != path else ".",
              "points": int(xyz.shape[0]), "image_folder": "images" if factor == 1 else f"images_{factor}"},
    )


def triangulated(tracks: list, centers: dict[int, np.ndarray], xyz: np.ndarray,
                 min_angle: float = MIN_TRIANGULATION_DEGREES) -> np.ndarray:
    """Points whose track (``(image_id, point2D_idx)`` rows) sees them from two registered cameras (``centers`` by
    image id) at least ``min_angle`` degrees apart: their depth is pinned down by the poses. Points seen from
    nearly one direction (the far end of a street, the sky's edge) are triangulated within a wide range of depths
    and would stretch the bounds and depth ranges toward infinity. ``# [P]`` bool"""
    keep = np.zeros(len(xyz), bool)
    cos_min = np.cos(np.radians(min_angle))
    for i, (track, x) in enumerate(zip(tracks, xyz)):
        c = np.array([centers[j] for j in np.asarray(track)[:, 0] if j in centers])  # [T, 3]
        if len(c) < 2:
            continue
        r = x - c
        r /= np.linalg.norm(r, axis=1, keepdims=True).clip(1e-12)
        keep[i] = (r @ r.T).min() <= cos_min
    return keep


def _image_folder(root: Path, names: list[str], cameras: Cameras, downscale: float) -> tuple[int, float]:
    """``(N, remaining downscale)``: the ``images_<N>`` folder to read (1 = ``images``) for ``downscale``.

    A folder counts only when it holds every image at exactly the cameras' size divided by N.
    """
    best = 1
    for d in root.glob("images_*"):
        n = d.name[len("images_"):]
        if not (n.isdigit() and 1 < int(n) <= downscale * (1 + 1e-9) and int(n) > best):
            continue
        small = cameras.rescaled(1.0 / int(n))
        try:
            common_size([d / name for name in names], (small.width, small.height), "the cameras give")
        except InputError:
            continue  # incomplete or another size: read images/ instead
        best = int(n)
    return best, downscale / best


def _near_far(cameras: Cameras, images, ids: np.ndarray, xyz: torch.Tensor, source: Path):
    """Per-view depth percentiles of the observed (else visible) points. ``near, far # [N]``"""
    order = np.argsort(ids)
    near = torch.full((len(images),), float("nan"), dtype=torch.float64)
    far = near.clone()
    for i, im in enumerate(images):
        obs = im.point3D_ids[im.point3D_ids >= 0]
        rows = order[np.clip(np.searchsorted(ids, obs, sorter=order), 0, len(ids) - 1)]
        rows = torch.from_numpy(rows[ids[rows] == obs])
        z = cameras[i].project(xyz[rows]).depth[0]
        z = z[z > 0]
        if z.numel() < MIN_POINTS:
            p = cameras[i].project(xyz)
            z = p.depth[0][p.in_image[0]]
        if z.numel() >= MIN_POINTS:
            lo, hi = np.percentile(z.numpy(), [1, 99])
            near[i], far[i] = 0.9 * lo, 1.1 * hi
    ok = torch.isfinite(near)
    if not ok.any():
        raise InputError("no view sees enough 3-D points to bound its depth", source,
                         "check that the points and poses belong together")
    near[~ok], far[~ok] = near[ok].median(), far[ok].median()
    return near, far
