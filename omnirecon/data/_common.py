"""Machinery every reader shares: view selection, image stacks, undistortion, bounds, assembly.

A reader parses its own pose files into full-length arrays (all views, at the resolution of the
files), then calls :func:`assemble`, which picks the views ``ReadOptions`` asks for and decodes only
their images. Scene-wide quantities (``bounds``, per-view ``near``/``far``) are computed by the
reader from all views, so they do not depend on which views are loaded.

Size: the helpers every reader shares (image loading, pose checks, splits, rig detection, paths kept
inside the scene folder); one module so that every reader applies the same checks.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from omnirecon.cameras import Cameras, check_poses, orthonormalize
from omnirecon.data.io import list_images, read_image
from omnirecon.data.scene import Scene
from omnirecon.errors import InputError
from omnirecon.splits import DTU_SOURCES, dtu_held_out

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".exr", ".webp")
BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


# ---------------------------------------------------------------------- poses
def pose_matrix(value, source: Path, what: str) -> np.ndarray:
    """A 4x4 float64 matrix from a nested list (3x4 gets the row ``[0 0 0 1]``); InputError otherwise."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{what} is not a numeric matrix", source, "give a 4x4 list of numbers") from e
    if m.shape == (3, 4):
        m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]])
    if m.shape != (4, 4):
        raise InputError(f"{what} has shape {'x'.join(map(str, m.shape)) or 'scalar'}, expected 4x4", source,
                         "give one 4x4 (or 3x4) camera-to-world matrix")
    return m


def rigid_poses(c2w: Tensor, source: Path) -> Tensor:
    """Validate camera-to-world poses ``# [N, 4, 4]`` (finite, rigid, det +1) and remove numerical noise."""
    check_poses(c2w, source)
    return orthonormalize(c2w.double())


# ---------------------------------------------------------------------- images on disk
def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image from its header; InputError if missing or not an image."""
    from omnirecon.data.photo import open_photo

    with open_photo(Path(path)) as im:  # regular file; the header's size checked against the limits
        return im.size


def common_size(paths: list[Path], expected: tuple[int, int] | None = None, expected_from: str = "") -> tuple[int, int]:
    """The one ``(width, height)`` that all ``paths`` share (and ``expected``, when given).

    The first image of a different size raises InputError naming it.
    """
    if not paths:
        raise InputError("no images listed", None, "list at least one image in the pose file")
    ref = expected
    for p in paths:
        size = image_size(p)
        if ref is None:
            ref, expected_from = size, f"{Path(paths[0]).name} is"
        elif size != tuple(ref):
            raise InputError(f"image is {size[0]}x{size[1]} but {expected_from} {ref[0]}x{ref[1]}", p,
                             "all views must share one image size; resize the image or fix the intrinsics")
    return int(ref[0]), int(ref[1])


def inside(folder: Path, rel: str, source: Path | None = None) -> Path:
    """``folder / rel`` when it stays inside ``folder`` (no absolute path, no ``..`` climbing out, no NUL);
    InputError naming ``source`` (the pose file that lists ``rel``) otherwise."""
    if not isinstance(rel, str):
        raise InputError(f"image path must be a string, got {type(rel).__name__}", source or folder,
                         "give each image as a relative path string, e.g. \"images/0001.png\"")
    try:
        too_long = any(len(part.encode()) > 255 for part in rel.split("/"))
    except UnicodeEncodeError:
        too_long = True
    if too_long:
        raise InputError(f"image path {rel[:40]!r}... is not a valid file name (too long or not encodable)",
                         source or folder, "give image paths as relative file names of at most 255 bytes each")
    target = os.path.normpath(os.path.join(os.path.abspath(folder), rel)) if "\0" not in rel else ""
    if not rel or os.path.isabs(rel) or not target.startswith(os.path.abspath(folder) + os.sep):
        raise InputError(f"image path {rel[:80]!r} points outside the scene folder", source or folder,
                         "give image paths relative to the scene folder, without '..' (copy or link the images in)")
    return Path(folder) / rel


def resolve_image(folder: Path, rel: str, source: Path | None = None) -> Path:
    """``folder / rel``, appending ``.png`` when ``rel`` has no image extension (Blender ``file_path``);
    ``rel`` must stay inside ``folder`` (:func:`inside`)."""
    p = inside(folder, rel, source)
    if p.suffix.lower() in IMAGE_EXTS or p.is_file():
        return p
    return p.with_name(p.name + ".png")


def _map(fn, items):
    workers = min(8, os.cpu_count() or 1, max(1, len(items)))
    if workers == 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(fn, items))


def read_rgb(paths: list[Path], size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray | None]:
    """Decode colour images at ``size = (W, H)`` (area averaging). Returns ``rgb # [N, H, W, 3]`` and
    straight ``alpha # [N, H, W]`` (``None`` when no image has an alpha channel)."""
    w, h = size
    rgb = np.empty((len(paths), h, w, 3), np.float32)

    def load(i):
        a = read_image(paths[i], size=size)  # [H, W, C]
        rgb[i] = a[..., :3] if a.shape[2] >= 3 else a[..., :1]
        return a[..., -1].copy() if a.shape[2] in (2, 4) else None

    alphas = _map(load, range(len(paths)))
    if all(a is None for a in alphas):
        return rgb, None
    return rgb, np.stack([np.ones((h, w), np.float32) if a is None else a for a in alphas])


def mask_files(root: Path, factor: int, images: list[Path]) -> list[Path] | None:
    """Mask per image from ``root/masks_<factor>/`` (or ``masks/`` at factor 1), matched by stem (``IMG_1.png``
    or COLMAP's ``IMG_1.jpg.png`` for ``IMG_1.jpg``); None without that folder."""
    folder = Path(root) / ("masks" if factor == 1 else f"masks_{factor}")
    if not folder.is_dir():
        return None
    by_stem = {}
    for p in list_images(folder):
        by_stem.setdefault(p.stem, p)
        if Path(p.stem).suffix.lower() in IMAGE_EXTS:
            by_stem.setdefault(Path(p.stem).stem, p)
    missing = [p for p in images if Path(p).stem not in by_stem]
    if missing:
        raise InputError(f"no mask for image {Path(missing[0]).name}", folder,
                         f"give one mask per image with the same stem ({', '.join(IMAGE_EXTS[:2])}), or remove the folder")
    return [by_stem[Path(p).stem] for p in images]


def read_masks(paths: list[Path], size: tuple[int, int]) -> np.ndarray:
    """Binary masks (``> 127`` of 8 bits, after area averaging to ``size``). ``# [N, H, W]`` bool"""
    return np.stack(_map(lambda p: read_image(p, mode="L", size=size)[..., 0] > 0.5, paths))


def read_raw(paths: list[Path], size: tuple[int, int], mode: str) -> np.ndarray:
    """Exact stored values (no filtering), nearest-neighbour resampled to ``size``. ``# [N, H, W, C]``

    ``mode="I"`` gives integer maps (depth, labels) as float64 integers, ``"RGB"`` 8-bit colour as 0..255.
    The nearest source pixel is the one holding the new pixel's centre.
    """
    w, h = size

    def load(p):
        a = read_image(p, mode=mode).astype(np.float64)  # [H0, W0, C]
        a = np.rint(a * (65535.0 if mode == "I" else 255.0))
        h0, w0 = a.shape[:2]
        if (w0, h0) != (w, h):
            rows = np.minimum(((np.arange(h) + 0.5) * h0 / h).astype(int), h0 - 1)
            cols = np.minimum(((np.arange(w) + 0.5) * w0 / w).astype(int), w0 - 1)
            a = a[rows][:, cols]
        return a

    return np.stack(_map(load, paths))


# ---------------------------------------------------------------------- distortion
def distort(x: Tensor, y: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
    """OpenCV radial-tangential model on normalised coordinates.

    ``d = (k1, k2, k3, k4, p1, p2)``: radial ``1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8`` (polynomial, as
    OpenCV's 5-parameter model extended by nerfstudio's ``k4``) and tangential ``p1, p2``.
    """
    k1, k2, k3, k4, p1, p2 = d.unbind(-1)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def undistort(images: Tensor, cams: Cameras, dist: Tensor) -> Tensor:
    """Resample distorted images onto the pinhole cameras ``cams`` (same K).

    Each output pixel centre is lifted to normalised coordinates with ``K``, pushed through
    :func:`distort` and sampled bilinearly from the input (pixels that map outside become 0).

    Args:
        images: ``# [N, H, W, C]`` float.
        dist: ``(k1, k2, k3, k4, p1, p2)`` per view. ``# [N, 6]``
    """
    out = images.clone()
    uv = cams.pixel_centers()  # [H, W, 2]
    for i in torch.nonzero(dist.abs().amax(dim=1) > 0)[:, 0].tolist():
        x = (uv[..., 0] - cams.cx[i]) / cams.fx[i]
        y = (uv[..., 1] - cams.cy[i]) / cams.fy[i]
        xd, yd = distort(x, y, dist[i].to(x))
        u, v = cams.fx[i] * xd + cams.cx[i], cams.fy[i] * yd + cams.cy[i]
        # align_corners=False: grid -1 / +1 are the outer pixel edges, i.e. u = 0 / u = W
        grid = torch.stack([2 * u / cams.width - 1, 2 * v / cams.height - 1], dim=-1)[None].float()
        src = images[i].permute(2, 0, 1)[None].float()  # [1, C, H, W]
        res = torch.nn.functional.grid_sample(src, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        out[i] = res[0].permute(1, 2, 0).to(out.dtype)
    return out


# ---------------------------------------------------------------------- splits and views
def holdout_splits(n: int, every: int = 8) -> dict[str, list[int]]:
    """LLFF convention (``llffhold``): every ``every``-th view (0, 8, 16, ...) is test, the rest train."""
    test = list(range(0, n, every))
    return {"train": [i for i in range(n) if i % every], "test": test}


def dtu_splits(n: int) -> dict[str, list[int]]:
    """A DTU scan's splits: ``test`` = the DTU protocol's held-out views (:func:`omnirecon.splits.dtu_held_out`)
    for a full scan (more views than the fixed sources need), else every 8th view; ``train`` = the rest."""
    if n <= max(DTU_SOURCES):
        return holdout_splits(n)
    test = dtu_held_out(n)
    return {"train": [i for i in range(n) if i not in set(test)], "test": test}


def select_views(n: int, splits: dict[str, list[int]], options, source: Path) -> tuple[list[int], dict[str, list[int]]]:
    """Views to load for ``options.splits``/``max_views``, and the splits re-indexed to them."""
    splits = {k: list(v) for k, v in splits.items() if k != "all"}
    keep = list(range(n))
    if options.splits:
        missing = [s for s in options.splits if s != "all" and s not in splits]
        if missing:
            raise InputError(f"scene has no split {missing[0]!r} (it has {['all', *sorted(splits)]})", source,
                             "choose one of the listed splits")
        if "all" not in options.splits:
            keep = sorted(set().union(*(splits[s] for s in options.splits)))
    if options.max_views is not None:
        if options.max_views < 1:
            raise InputError(f"--max-views must be at least 1, got {options.max_views}", None,
                             "use e.g. --max-views 40, or leave it out for all views")
        if len(keep) > options.max_views:
            pick = np.unique(np.linspace(0, len(keep) - 1, options.max_views).round().astype(int))
            keep = [keep[i] for i in pick]
    if not keep:
        raise InputError("no views selected", source, "choose a split that has views")
    remap = {old: new for new, old in enumerate(keep)}
    out = {k: [remap[i] for i in v if i in remap] for k, v in splits.items()}
    return keep, {k: v for k, v in out.items() if v}


# ---------------------------------------------------------------------- geometry
def box_corners(box: Tensor) -> Tensor:
    """The 8 corners of an AABB ``# [2, 3]``. ``# [8, 3]``"""
    idx = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)])
    return box[idx, torch.arange(3)]


def near_far_from_box(cams: Cameras, box: Tensor, min_near: float = 0.01) -> tuple[Tensor, Tensor]:
    """Per-view z-depth range of an AABB (its corners): ``near, far # [N]``.

    ``near`` is clamped to ``min_near x far`` when the camera sits inside the box.
    """
    z = cams.project(box_corners(box.double())).depth  # [N, 8]
    far = z.amax(dim=1)
    near = torch.maximum(z.amin(dim=1), min_near * far)
    return near, far


def frustum_box(cams: Cameras, near: Tensor, far: Tensor, region: Tensor | None = None,
                fraction: float = 0.9, res: int = 40) -> Tensor:
    """AABB ``# [2, 3]`` of the points seen by at least ``fraction`` of the views within their
    ``[near, far]`` depth range: the content every camera looks at.

    The points are a ``res^3`` grid over ``region`` (default: the union of all view frustums),
    refined once inside the first estimate. Falls back to ``region`` when no grid point qualifies.
    """
    if region is None:
        corners = []
        for depth in (near, far):
            w, h = cams.width, cams.height
            uv = torch.tensor([[0, 0], [w, 0], [0, h], [w, h]], dtype=torch.float64)
            corners.append(cams.unproject(uv.expand(len(cams), 4, 2), depth.double()[:, None].expand(-1, 4)))
        pts = torch.cat(corners, dim=1).reshape(-1, 3)
        region = torch.stack([pts.amin(0), pts.amax(0)])
    region = region.double()
    w2c = cams.w2c.float()  # [N, 4, 4]
    K = cams.K.float()  # [N, 3, 3]
    need = math.ceil(fraction * len(cams))
    box = region
    for _ in range(2):
        axes = [torch.linspace(float(box[0, k]), float(box[1, k]), res, dtype=torch.float64) for k in range(3)]
        grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)  # [P, 3]
        count = torch.zeros(grid.shape[0], dtype=torch.int32)
        g = torch.cat([grid.float(), torch.ones(len(grid), 1)], 1)  # [P, 4]
        for v in range(0, len(cams), 16):  # chunks of views: few large ops, bounded memory
            x = g @ (K[v:v + 16] @ w2c[v:v + 16, :3]).transpose(1, 2)  # [C, P, 3] = (z u, z v, z)
            z = x[..., 2]
            ok = (z >= near[v:v + 16, None].float()) & (z <= far[v:v + 16, None].float()) \
                & (x[..., 0] >= 0) & (x[..., 0] < cams.width * z) & (x[..., 1] >= 0) & (x[..., 1] < cams.height * z)
            count += ok.sum(0, dtype=torch.int32)
        inside = grid[count >= need]
        if inside.shape[0] == 0:
            return box.float()
        cell = (box[1] - box[0]) / (res - 1)
        box = torch.stack([inside.amin(0) - cell, inside.amax(0) + cell])
        box = torch.stack([torch.maximum(box[0], region[0]), torch.minimum(box[1], region[1])])
    return box.float()


def detect_rig(cams: Cameras, threshold: float = 0.9) -> str:
    """``"object"`` when the optical axes spread (the mean of the unit forward vectors is shorter than
    ``threshold``, i.e. they deviate from their mean by more than ~25° on average), else ``"forward"``.

    Forward-facing LLFF captures score above 0.97; 360° rigs near 0; hand-held arcs around an
    object (instant-ngp's fox, DTU's 49 views) about 0.82.
    """
    return "object" if float(cams.forward.mean(0).norm()) < threshold else "forward"


# ---------------------------------------------------------------------- assembly
def assemble(
    *,
    path: Path,
    fmt: str,
    cameras: Cameras,
    image_paths: list[Path],
    near: Tensor,
    far: Tensor,
    bounds: Tensor,
    splits: dict[str, list[int]],
    options,
    rig: str,
    source: Path,
    mask_paths: list[Path] | None = None,
    distortion: Tensor | None = None,
    depth_paths: list[Path] | None = None,
    depth_scale: float = 1.0,
    normal_paths: list[Path] | None = None,
    label_paths: list[Path] | None = None,
    background: tuple[float, float, float] | None = None,
    to_input: Tensor | None = None,
    mesh_path: Path | None = None,
    meta: dict | None = None,
) -> Scene:
    """Load the selected views' images (and maps) and return the validated :class:`Scene`.

    ``cameras`` are at the files' resolution (all views); ``near``/``far`` ``# [N]``; ``bounds # [2, 3]``.
    ``distortion # [N, 6]`` (see :func:`distort`) undistorts images and masks. Per-view path lists
    may contain ``None`` for views without that map (the map is then 0 / unknown there).
    """
    ds = float(options.downscale)
    if not (math.isfinite(ds) and ds > 0):
        raise InputError(f"downscale must be a positive number, got {options.downscale}", None,
                         "use e.g. --downscale 2")
    keep, splits = select_views(len(cameras), splits, options, source)
    cams = cameras[keep]
    if ds != 1.0:
        cams = cams.rescaled(1.0 / ds)
    size = (cams.width, cams.height)
    pick = lambda lst: [lst[i] for i in keep]  # noqa: E731

    rgb, alpha = read_rgb(pick(image_paths), size)
    images = torch.from_numpy(rgb)  # [N, H, W, 3]
    if alpha is not None:
        background = BACKGROUNDS[options.background]
        a = torch.from_numpy(alpha)[..., None]  # [N, H, W, 1]
        images = images * a + torch.tensor(background, dtype=torch.float32) * (1 - a)
    masks = None
    if mask_paths is not None:
        common_size(mask_paths, (cameras.width, cameras.height), "the images are")
        masks = torch.from_numpy(read_masks(pick(mask_paths), size))
    elif alpha is not None:
        masks = torch.from_numpy(alpha > 0.5)
    if distortion is not None and (distortion[keep] != 0).any():
        images = undistort(images, cams, distortion[keep].double())
        if masks is not None:
            masks = undistort(masks[..., None].float(), cams, distortion[keep].double())[..., 0] > 0.5

    def maps(paths, mode):
        if paths is None:
            return None
        sel = pick(paths)
        present = [p for p in sel if p is not None]
        if not present:
            return None
        common_size(present, (cameras.width, cameras.height), "the images are")
        got = read_raw(present, size, mode)  # [M, H, W, C]
        out = np.zeros((len(sel), *got.shape[1:]), got.dtype)
        out[[i for i, p in enumerate(sel) if p is not None]] = got
        return out

    depths = maps(depth_paths, "I")
    if depths is not None:
        depths = torch.from_numpy(depths[..., 0] * depth_scale).float()  # [N, H, W]
    normals = maps(normal_paths, "RGB")
    if normals is not None:
        n = torch.from_numpy(normals * (2.0 / 255.0) - 1.0)  # [N, H, W, 3]
        length = n.norm(dim=-1, keepdim=True)
        valid = (length > 0.5) & (length < 1.5)  # unit normals; (0,0,0) and (128,128,128) mark "none"
        normals = torch.where(valid, n / length.clamp_min(1e-12), torch.zeros_like(n)).float()
    labels = maps(label_paths, "I")
    if labels is not None:
        labels = torch.from_numpy(labels[..., 0]).long()  # [N, H, W]

    scene = Scene(
        images=images.float().contiguous(), cameras=cams, near=near[keep].double(), far=far[keep].double(),
        bounds=bounds.float(), splits=splits, masks=masks, depths=depths, normals=normals, labels=labels,
        names=[_name(p, path) for p in pick(image_paths)], format=fmt, path=path, rig=rig,
        background=None if background is None else tuple(float(c) for c in background),
        mesh_path=mesh_path, meta=dict(meta or {}),
        **({} if to_input is None else {"to_input": to_input.double()}),
    )
    scene.validate()
    return scene


def _name(p: Path, root: Path) -> str:
    try:
        return str(Path(p).relative_to(root))
    except ValueError:
        return Path(p).name
