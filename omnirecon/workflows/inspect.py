"""``omnirecon inspect``: validate a scene, summarise it, draw its cameras and check its poses.

Consistency scores (all computed from the data, nothing assumed):

* ``epipolar_px`` — every scene: SIFT features matched between neighbouring views; median distance
  (pixels) of each match from the epipolar line the poses predict (symmetric). A few pixels or less
  means poses and intrinsics agree with the images; mirrored or mis-scaled poses give tens.
* ``depth_reproj_px`` — scenes with depth: pixels of view A lifted with A's depth, projected into a
  neighbour B, lifted again with B's depth and projected back to A; the median round-trip error in
  pixels over pixels visible in both views.
* ``hull_fraction`` — scenes with masks: the fraction of foreground pixels whose ray meets the
  visual hull carved from the *other* views' masks (a point is carved away when it projects inside
  another view's image but outside its mask). 1.0 is perfect.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro
from torch import Tensor

from omnirecon.cameras import Cameras, nearest_views
from omnirecon.data import Format, ReadOptions, load_scene
from omnirecon.data.io import atomic_path, write_json
from omnirecon.data.scene import Scene
from omnirecon.errors import InputError
from omnirecon.options import OutFolder, Seeded, ViewLimit, check_options
from omnirecon.scene_kind import scene_kind


@dataclass
class InspectConfig(OutFolder, Seeded, ViewLimit):
    """Validate a scene, print a summary, write pictures of its cameras and epipolar lines, and
    print numeric pose-consistency scores."""

    path: tyro.conf.Positional[Path]
    """Scene folder (any supported format)."""
    format: Format = "auto"
    """Force a reader instead of detecting the format."""
    downscale: float = 1.0
    """Divide the image resolution by this factor while loading (faster on large captures)."""
    pair: tuple[int, int] | None = None
    """View pair for the epipolar picture (default: view 0 and its nearest neighbour)."""
    num_pairs: int = 4
    """How many neighbouring view pairs the consistency scores average over."""
def default_out(cfg: InspectConfig) -> Path:
    """The output folder when --out is not given."""
    return Path("outputs/inspect") / Path(cfg.path).resolve().name


def run_inspect(cfg: InspectConfig, folder: Path | None = None) -> dict:
    """Validate and summarise the scene; pictures and ``summary.json`` go to ``folder`` (default: --out; the
    command passes the temporary twin that :func:`omnirecon.outputs.claim` swaps in), messages name --out."""
    from rich.console import Console
    from rich.table import Table

    console = Console()
    check_options("inspect", cfg)  # the numbers (omnirecon/options.py); here for callers other than the CLI
    scene = load_scene(cfg.path, cfg.format, ReadOptions(downscale=cfg.downscale, max_views=cfg.max_views))
    if len(scene) < 2:
        raise InputError(f"scene has {len(scene)} view(s); inspection needs at least 2", cfg.path,
                         "add views, or raise --max-views")
    out = cfg.out or default_out(cfg)
    folder = folder or out
    summary = scene.summary()
    pairs = neighbour_pairs(scene, cfg.num_pairs)
    a, b = cfg.pair if cfg.pair is not None else pairs[0]
    if not (0 <= a < len(scene) and 0 <= b < len(scene)) or a == b:
        raise InputError(f"--pair {a} {b} is not two different views in 0..{len(scene) - 1}", cfg.path,
                         "pass two distinct view indices")

    g = torch.Generator().manual_seed(cfg.seed)
    epi, matches = epipolar_score(scene, pairs)
    scores: dict[str, float | int | None] = {"epipolar_px": epi, "epipolar_matches": matches}
    if scene.depths is not None:
        scores["depth_reproj_px"] = depth_reprojection_score(scene, pairs, g)
    if scene.masks is not None:
        scores["hull_fraction"] = visual_hull_score(scene, g)
    summary["consistency"] = scores

    draw_cameras(scene, folder / "cameras.png")
    draw_epipolar(scene, a, b, folder / "epipolar.png")
    write_json(folder / "summary.json", summary)

    table = Table(title=f"{scene.path}", show_header=False)
    for k, v in summary.items():
        if k != "consistency":
            table.add_row(k, json.dumps(v))
    for k, v in scores.items():
        table.add_row(f"consistency.{k}", "n/a" if v is None else f"{v:.4g}")
    console.print(table)
    console.print(f"wrote {out / 'cameras.png'}, {out / 'epipolar.png'}, {out / 'summary.json'}")
    return summary


# ---------------------------------------------------------------------- geometry helpers
def neighbour_pairs(scene: Scene, count: int) -> list[tuple[int, int]]:
    """``count`` (view, nearest other view) pairs spread over the capture."""
    n = len(scene)
    views = np.linspace(0, n - 1, min(count, n)).round().astype(int).tolist()
    by = scene_kind(scene).rank_by
    cams = scene.cameras
    nn = nearest_views(cams[views], cams, 1, by=by, exclude=torch.tensor(views))[:, 0]
    return [(a, int(b)) for a, b in zip(views, nn)]


def fundamental(cams: Cameras, a: int, b: int) -> Tensor:
    """Fundamental matrix ``F`` with ``x_b^T F x_a = 0`` for homogeneous pixels (``+0.5`` centres). ``# [3, 3]``"""
    rel = cams.w2c[b] @ cams.c2w[a]  # camera a -> camera b
    R, t = rel[:3, :3], rel[:3, 3]
    tx = torch.tensor([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]], dtype=R.dtype)
    K = cams.K
    return torch.linalg.inv(K[b]).T @ tx @ R @ torch.linalg.inv(K[a])


def _line_distance(F: Tensor, xa: Tensor, xb: Tensor) -> Tensor:
    """Symmetric point-to-epipolar-line distance (pixels) for matches ``xa, xb # [M, 2]``. ``# [M]``"""
    ha = torch.cat([xa, torch.ones_like(xa[:, :1])], 1)
    hb = torch.cat([xb, torch.ones_like(xb[:, :1])], 1)
    lb = ha @ F.T  # lines in b
    la = hb @ F  # lines in a
    num = (hb * lb).sum(1).abs()
    return 0.5 * (num / lb[:, :2].norm(dim=1).clamp_min(1e-12) + num / la[:, :2].norm(dim=1).clamp_min(1e-12))


def epipolar_score(scene: Scene, pairs: list[tuple[int, int]], min_matches: int = 8) -> tuple[float | None, int]:
    """Median symmetric epipolar distance (px) of cross-checked SIFT matches over ``pairs``, and the
    number of matches (``None`` when fewer than ``min_matches``). Images under 300 px are upsampled
    2x for detection; distances are in the scene's own pixels."""
    from skimage.color import rgb2gray
    from skimage.feature import SIFT, match_descriptors
    from skimage.transform import rescale

    up = 2 if max(scene.width, scene.height) < 300 else 1
    cams = scene.cameras.to(dtype=torch.float64)
    dists = []
    for a, b in pairs:
        feats = []
        for i in (a, b):
            gray = rgb2gray(scene.images[i].numpy())
            sift = SIFT()
            try:
                sift.detect_and_extract(rescale(gray, up, order=1) if up > 1 else gray)
            except RuntimeError:  # no keypoints (e.g. a flat image)
                break
            # skimage gives (row, col) of pixel indices at the detection scale; ours are centres at +0.5
            feats.append(((torch.from_numpy(sift.keypoints[:, ::-1].copy()).double() + 0.5) / up, sift.descriptors))
        if len(feats) < 2:
            continue
        m = match_descriptors(feats[0][1], feats[1][1], cross_check=True, max_ratio=0.8)
        if len(m):
            dists.append(_line_distance(fundamental(cams, a, b), feats[0][0][m[:, 0]], feats[1][0][m[:, 1]]))
    d = torch.cat(dists) if dists else torch.zeros(0)
    return (float(d.median()) if len(d) >= min_matches else None), len(d)


def _sample_nearest(image: Tensor, uv: Tensor) -> Tensor:
    """Nearest-pixel lookup of ``image # [H, W, ...]`` at continuous ``uv # [P, 2]``."""
    h, w = image.shape[:2]
    col = uv[:, 0].floor().long().clamp(0, w - 1)
    row = uv[:, 1].floor().long().clamp(0, h - 1)
    return image[row, col]


def depth_reprojection_score(scene: Scene, pairs, g: torch.Generator, samples: int = 4000) -> float | None:
    """Median round-trip reprojection error (px) of depth-warped pixels over ``pairs``."""
    cams = scene.cameras.to(dtype=torch.float64)
    errs = []
    for a, b in pairs:
        da, db = scene.depths[a].double(), scene.depths[b].double()
        rows, cols = torch.nonzero(da > 0, as_tuple=True)
        if len(rows) == 0:
            continue
        pick = torch.randint(len(rows), (min(samples, len(rows)),), generator=g)
        uv_a = torch.stack([cols[pick], rows[pick]], 1).double() + 0.5  # [P, 2]
        pts = cams[[a]].unproject(uv_a[None], da[rows[pick], cols[pick]][None])  # [1, P, 3]
        proj = cams[[b]].project(pts[0])
        z_b = _sample_nearest(db, proj.uv[0])
        visible = proj.in_image[0] & (z_b > 0) & ((proj.depth[0] - z_b).abs() < 0.01 * z_b + 1e-6)
        if visible.sum() < 10:
            continue
        back = cams[[b]].unproject(proj.uv[:, visible], z_b[visible][None])
        uv_back = cams[[a]].project(back[0]).uv[0]
        errs.append((uv_back - uv_a[visible]).norm(dim=1))
    if not errs:
        return None
    return float(torch.cat(errs).median())


def visual_hull_score(scene: Scene, g: torch.Generator, views: int = 8, rays: int = 400,
                      samples: int = 384, tolerance_px: int = 1) -> float | None:
    """Fraction of foreground rays of up to ``views`` views that meet the other views' visual hull.

    Samples ``samples`` points per ray between near and far; a point is carved when it projects
    inside another view's image but outside its mask dilated by ``tolerance_px`` (silhouettes are
    uncertain by about a pixel, and a grazing ray's sample rarely falls exactly on the surface).
    """
    import torch.nn.functional as F

    cams = scene.cameras
    n = len(scene)
    k = 2 * tolerance_px + 1
    masks = F.max_pool2d(scene.masks[:, None].float(), k, stride=1, padding=tolerance_px)[:, 0] > 0  # [N, H, W]
    hits, total = 0, 0
    for i in np.linspace(0, n - 1, min(views, n)).round().astype(int).tolist():
        rows, cols = torch.nonzero(scene.masks[i], as_tuple=True)
        if len(rows) == 0:
            continue
        pick = torch.randint(len(rows), (min(rays, len(rows)),), generator=g)
        uv = torch.stack([cols[pick], rows[pick]], 1).to(cams.c2w) + 0.5
        o, d = cams[[i]].rays(uv[None], normalize=False)  # z-depth parameterisation
        z = torch.linspace(float(scene.near[i]), float(scene.far[i]), samples, dtype=d.dtype)
        pts = (o[0, :, None] + d[0, :, None] * z[:, None]).reshape(-1, 3)  # [P*S, 3]
        others = torch.tensor([j for j in range(n) if j != i])
        proj = cams[others].project(pts)  # [N-1, P*S]
        col = proj.uv[..., 0].floor().long().clamp(0, scene.width - 1)
        row = proj.uv[..., 1].floor().long().clamp(0, scene.height - 1)
        seen_in_mask = masks[others[:, None], row, col]  # [N-1, P*S]
        inside = (~proj.in_image | seen_in_mask).all(0)  # [P*S]
        hits += int(inside.reshape(len(pick), samples).any(1).sum())
        total += len(pick)
    return hits / total if total else None


# ---------------------------------------------------------------------- pictures
def _frustum_lines(cams: Cameras, size: float) -> np.ndarray:
    """Line segments of each camera's frustum drawn at z-depth ``size``. ``# [N, 8, 2, 3]``"""
    w, h = cams.width, cams.height
    corners = torch.tensor([[0, 0], [w, 0], [w, h], [0, h]], dtype=cams.c2w.dtype)
    pts = cams.unproject(corners.expand(len(cams), 4, 2), torch.full((len(cams), 4), size, dtype=cams.c2w.dtype))
    c = cams.centers[:, None].expand(-1, 4, -1)
    rim = torch.stack([pts, pts.roll(-1, dims=1)], 2)  # [N, 4, 2, 3]
    spokes = torch.stack([c, pts], 2)  # [N, 4, 2, 3]
    return torch.cat([spokes, rim], 1).numpy()


def _box_lines(bounds: Tensor) -> np.ndarray:
    lo, hi = bounds[0].tolist(), bounds[1].tolist()
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return np.array([[corners[a], corners[b]] for a, b in edges])


def draw_cameras(scene: Scene, path: Path) -> None:
    """Camera frustums coloured by split, with the scene bounds, in a 3-D view and a top view."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cams = scene.cameras.to(dtype=torch.float64)
    extent = float(np.ptp(torch.cat([cams.centers, scene.bounds.double()]).numpy(), axis=0).max())
    lines = _frustum_lines(cams, 0.06 * extent)
    split_of = np.full(len(scene), "all", dtype=object)
    for name in ("train", "val", "test"):
        for i in scene.splits.get(name, []):
            split_of[i] = name
    box = _box_lines(scene.bounds.double())
    fig = plt.figure(figsize=(12, 6), dpi=100)
    _cameras_3d(fig.add_subplot(1, 2, 1, projection="3d"), lines, box, split_of)
    _cameras_top(fig.add_subplot(1, 2, 2), cams, lines, box, split_of)
    fig.suptitle(f"{scene.format}: {len(scene)} views, {scene.width}x{scene.height}, rig={scene.rig}")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


SPLIT_COLOURS = {"train": "tab:blue", "val": "tab:orange", "test": "tab:red", "all": "tab:blue"}
"""Frustum colour per split in :func:`draw_cameras`."""


def _cameras_3d(ax, lines: np.ndarray, box: np.ndarray, split_of: np.ndarray) -> None:
    """The frustums (``lines``, ``# [N, L, 2, 3]``) and the bounds' ``box`` in a 3-D view."""
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    for name in dict.fromkeys(split_of):
        sel = split_of == name
        ax.add_collection3d(Line3DCollection(lines[sel].reshape(-1, 2, 3), colors=SPLIT_COLOURS[name], linewidths=0.8,
                                             label=f"{name} ({sel.sum()})"))
    ax.add_collection3d(Line3DCollection(box, colors="k", linewidths=1.0, label="bounds"))
    allp = np.concatenate([lines.reshape(-1, 3), box.reshape(-1, 3)])
    mid, half = (allp.max(0) + allp.min(0)) / 2, (allp.max(0) - allp.min(0)).max() / 2
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_xlabel("x"), ax.set_ylabel("y"), ax.set_zlabel("z")
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title("cameras (OpenCV frustums) and bounds, scene frame")


def _cameras_top(ax2, cams, lines: np.ndarray, box: np.ndarray, split_of: np.ndarray) -> None:
    """Top view: the two axes with the largest camera spread, with view indices."""
    from matplotlib.collections import LineCollection

    spread = np.ptp(cams.centers.numpy(), axis=0) if len(cams) > 1 else np.ones(3)
    i, j = sorted(np.argsort(spread)[-2:])
    for name in dict.fromkeys(split_of):
        sel = split_of == name
        seg = lines[sel][..., [i, j]].reshape(-1, 2, 2)
        ax2.add_collection(LineCollection(seg, colors=SPLIT_COLOURS[name], linewidths=0.8))
    ax2.add_collection(LineCollection(box[..., [i, j]], colors="k", linewidths=1.0))
    for k in np.linspace(0, len(cams) - 1, min(len(cams), 12)).round().astype(int):
        ax2.annotate(str(k), cams.centers[k, [i, j]].numpy(), fontsize=7)
    ax2.autoscale(), ax2.set_aspect("equal")
    ax2.set_xlabel("xyz"[i]), ax2.set_ylabel("xyz"[j])
    ax2.set_title(f"projection on the {'xyz'[i]}{'xyz'[j]} plane (view indices)")


def _corner_points(scene: Scene, a: int, count: int) -> torch.Tensor:
    """Up to ``count`` strong image corners of view ``a`` (inside its mask when there is one; a grid on a flat
    image), as continuous pixel coordinates. ``# [P, 2]``"""
    from skimage.color import rgb2gray
    from skimage.feature import corner_harris, corner_peaks

    resp = corner_harris(rgb2gray(scene.images[a].numpy()))
    if scene.masks is not None:
        resp = resp * scene.masks[a].numpy()
    peaks = corner_peaks(resp, min_distance=max(3, scene.width // 30), num_peaks=count)
    if len(peaks) < count:  # flat image: fall back to a grid
        ys, xs = np.meshgrid(np.linspace(0.2, 0.8, 3) * scene.height, np.linspace(0.2, 0.8, 4) * scene.width)
        peaks = np.stack([ys.ravel(), xs.ravel()], 1).astype(int)[:count]
    return torch.from_numpy(peaks[:, ::-1].copy()).double() + 0.5


def draw_epipolar(scene: Scene, a: int, b: int, path: Path, count: int = 12) -> None:
    """Points in view ``a`` (left) and their epipolar lines in view ``b`` (right).

    Points are picked on strong image corners (inside the mask when there is one). Where depth
    exists, the point's true position in ``b`` is marked on its line.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    uv = _corner_points(scene, a, count)
    F = fundamental(scene.cameras.to(dtype=torch.float64), a, b)
    lines = torch.cat([uv, torch.ones(len(uv), 1, dtype=uv.dtype)], 1) @ F.T  # [P, 3]
    fig, axes = plt.subplots(1, 2, figsize=(12, 6 * scene.height / scene.width + 0.6), dpi=100)
    colours = plt.cm.tab20(np.linspace(0, 1, len(uv)))
    # imshow with extent so that data coordinates are our continuous pixel coordinates
    ext = (0, scene.width, scene.height, 0)
    axes[0].imshow(scene.images[a].numpy(), extent=ext)
    axes[1].imshow(scene.images[b].numpy(), extent=ext)
    axes[0].scatter(uv[:, 0], uv[:, 1], c=colours, s=30, edgecolors="k")
    xs = np.array([0.0, scene.width])
    for (la, lb, lc), col in zip(lines.numpy(), colours):
        if abs(lb) > 1e-9:
            axes[1].plot(xs, -(la * xs + lc) / lb, color=col, linewidth=1.2)
        else:
            axes[1].axvline(-lc / la, color=col, linewidth=1.2)
    if scene.depths is not None:
        _mark_warped(axes[1], scene, a, b, uv, colours)
    for ax, i in zip(axes, (a, b)):
        ax.set_xlim(0, scene.width), ax.set_ylim(scene.height, 0)
        ax.set_title(f"view {i}: {scene.names[i]}")
        ax.axis("off")
    fig.suptitle("points in the left view lie on the lines of the same colour on the right"
                 + (" (x = depth-warped point)" if scene.depths is not None else ""))
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def _mark_warped(ax, scene: Scene, a: int, b: int, uv: torch.Tensor, colours) -> None:
    """Mark where the points ``uv`` of view ``a`` land in view ``b`` by their depth (an ``x`` each)."""
    z = _sample_nearest(scene.depths[a].double(), uv)
    ok = z > 0
    if ok.any():
        cams = scene.cameras.to(dtype=torch.float64)
        pts = cams[[a]].unproject(uv[ok][None], z[ok][None])
        pb = cams[[b]].project(pts[0]).uv[0]
        ax.scatter(pb[:, 0], pb[:, 1], c=colours[ok.numpy()], s=30, marker="x")
