"""DTU (and other IDR/NeuS scenes): ``cameras_sphere.npz`` (or IDR's ``cameras.npz``), ``image/``, ``mask/``.

Conventions:

* ``world_mat_i`` is a 4x4 projection ``K [R | t]`` (world -> pixels, OpenCV frame, world-to-camera);
  ``scale_mat_i`` maps the normalised space (object inside the unit sphere) to the world.
  ``P = world_mat_i @ scale_mat_i`` is split into K and a rigid pose by an RQ decomposition.
* The scene frame is the normalised space; ``to_input = scale_mat_0`` maps it back to DTU world
  units (millimetres). All ``scale_mat_i`` must agree.
* Pixel convention: K is used as stored (centres at +0.5). IDR/NeuS cast rays through integer
  pixel coordinates with the same K, so if the original calibration was integer-centred the exact
  principal point would be ``c + 0.5 s`` (0.125 px at 400x300); this reader does not shift it.
* ``near``/``far``: the z-depth range of the unit sphere, approximated by the distance range
  ``max(0.05, |C| - 1) .. |C| + 1`` of the camera centre C. ``bounds = [-1, 1]^3``. ``rig = "object"``.
* Images ``image/*`` and masks ``mask/*`` (3-channel, > 127 = object) pair in sorted order.
* Splits: only ``all`` and ``train = all``. The sparse-view protocol of pixelNeRF/RegNeRF
  (train views 25, 22, 28, 40, 44, 48, 0, 8, 13) is recorded in ``meta["pixelnerf_train"]``.
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np
import scipy.linalg
import torch

from omnirecon.cameras import Cameras
from omnirecon.data._common import assemble, common_size, dtu_splits, rigid_poses
from omnirecon.data.io import list_images, read_npy
from omnirecon.data.scene import Scene
from omnirecon.errors import InputError

NAME = "dtu_neus"
PIXELNERF_TRAIN = [25, 22, 28, 40, 44, 48, 0, 8, 13]


def detect(path: Path) -> bool:
    path = Path(path)
    return (path / "cameras_sphere.npz").is_file() or ((path / "cameras.npz").is_file() and (path / "image").is_dir())


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a 3x4 projection ``P = lambda K [R | t]`` into ``K # [3, 3]`` (positive diagonal, ``K[2, 2] = 1``)
    and the world-to-camera rigid ``[R | t] # [4, 4]`` (``det R = +1``)."""
    P = np.asarray(P, dtype=np.float64)
    M = P[:, :3]
    if np.linalg.det(M) < 0:  # P is only defined up to scale; pick the sign that makes R proper
        P, M = -P, -M
    K, R = scipy.linalg.rq(M)
    D = np.diag(np.sign(np.diag(K)))  # K D, D R keeps the product; makes diag(K) > 0
    K, R = K @ D, D @ R
    t = np.linalg.solve(K, P[:, 3])  # (lambda K)^-1 lambda K t
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, t
    return K / K[2, 2], w2c


def read(path: Path, options) -> Scene:
    """Read the scene at ``path`` (see the module docstring)."""
    path = Path(path)
    source = path / "cameras_sphere.npz"
    if not source.is_file():
        source = path / "cameras.npz"
    npz = read_npy(source)
    if not hasattr(npz, "files"):
        raise InputError("expected an .npz archive of world_mat_i / scale_mat_i arrays", source,
                         "regenerate the file with numpy.savez")
    if not (path / "image").is_dir() or not list_images(path / "image"):
        raise InputError("no images in image/", path / "image", "put the views in image/ as 000000.png, ...")
    images = list_images(path / "image")
    n = len(images)
    Ks, w2cs, scale_mats = [], [], []
    for i in range(n):
        world, scale = (_matrix(npz, f"{k}_{i}", source, n) for k in ("world_mat", "scale_mat"))
        try:
            K, w2c = decompose_projection((world @ scale)[:3, :4])
        except (np.linalg.LinAlgError, ValueError) as e:
            raise InputError(f"world_mat_{i} @ scale_mat_{i} is not a valid projection ({e})", source,
                             "give full-rank 4x4 matrices (world_mat = K [R | t]); regenerate the file") from e
        if abs(K[0, 1]) > 1e-3 * K[0, 0]:
            raise InputError(f"world_mat_{i} has pixel skew {K[0, 1]:.3g} (not supported by the pinhole model)", source,
                             "resample the images to square, unskewed pixels")
        Ks.append(K)
        w2cs.append(w2c)
        scale_mats.append(scale)
    scale_mats = np.stack(scale_mats)
    if np.abs(scale_mats - scale_mats[0]).max() > 1e-6 * np.abs(scale_mats[0]).max():
        raise InputError("scale_mat_i differ between views", source, "use one normalisation for all views")
    w2c = torch.from_numpy(np.stack(w2cs))
    c2w = rigid_poses(torch.linalg.inv(w2c), source)
    width, height = common_size(images)
    cameras = Cameras.from_K(torch.from_numpy(np.stack(Ks)), c2w, width, height)
    dist = cameras.centers.norm(dim=-1)
    near, far = (dist - 1).clamp_min(0.05), dist + 1
    masks = None
    if (path / "mask").is_dir():
        masks = list_images(path / "mask")
        if len(masks) != n:
            raise InputError(f"{len(masks)} masks but {n} images in image/", path / "mask",
                             "give one mask per image (sorted order pairs them)")
    return assemble(
        path=path, fmt=NAME, cameras=cameras, image_paths=images, near=near, far=far,
        bounds=torch.tensor([[-1.0] * 3, [1.0] * 3]), splits=dtu_splits(n), options=options,
        rig="object", source=source, mask_paths=masks, to_input=torch.from_numpy(scale_mats[0]),
        meta={"pixelnerf_train": [i for i in PIXELNERF_TRAIN if i < n]},
    )


def _matrix(npz, key: str, source: Path, n: int) -> np.ndarray:
    if key not in npz.files:
        raise InputError(f"missing key {key} ({n} images in image/)", source,
                         "give world_mat_i and scale_mat_i for every image")
    try:
        raw = np.asarray(npz[key])
        if raw.dtype.kind not in "fiub":  # complex, strings, objects: not a camera matrix
            raise ValueError(f"dtype {raw.dtype} is not real-valued")
        m = raw.astype(np.float64)
    except (ValueError, TypeError, OSError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError,
            RuntimeError) as e:  # zipfile: unsupported version/compression, encrypted member
        raise InputError(f"cannot read {key} ({e})", source, "regenerate the file") from e
    if m.shape == (3, 4):
        m = np.concatenate([m, [[0, 0, 0, 1.0]]])
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise InputError(f"{key} must be a finite 4x4 matrix, got shape {'x'.join(map(str, m.shape))}"
                         + ("" if m.shape != (4, 4) else " with NaN/Inf entries"), source,
                         "regenerate the file with finite 4x4 (or 3x4) matrices")
    return m
