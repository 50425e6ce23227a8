"""Classical multi-view stereo on the CPU: a depth source that needs no training.

For each view, a few neighbours with sideways baselines are picked (:func:`stereo_neighbours`); each pair is
rectified from the known poses (:func:`rectify_pair`: a common rotation whose x axis is the baseline, one focal
length; OpenCV's ``stereoRectify`` returned negative focal lengths on our cameras, see ``shared/docs/stereo.md``),
matched by OpenCV's semi-global matcher (``StereoSGBM``, ``MODE_SGBM_3WAY``: its left-right check ``disp12MaxDiff``
and uniqueness test drop ambiguous pixels; disparities come in 1/16 px), and the disparity is read back at the
view's own pixels (bilinear inside a surface, so the depth stays sub-pixel). The depths of the pairs are then voted
on (:func:`vote`): each pixel keeps the depth most pairs agree with (within ``agree``, relative) and a confidence
from that agreement, so an occluded or mismatched pair loses its vote.

Three details that matter: the disparity search range comes from the scene bounds (the depth range of the part of
the bounds box the view sees); the other image's canvas is shifted by the smallest disparity of that range, so that
converging cameras' correspondences stay on it (without it a pair 32 degrees apart on the demo scene read depths
far too far: what it sees at the canvas' left lay off the other canvas); and both images are padded on the left by
the search range, since SGBM leaves that band of the left image unmatched (on DTU the padding about triples the
pixels matched). Last, each view's depth is checked against the other views' maps
(``StereoOptions.confirm``): a depth no other view confirms is dropped.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError


@dataclass
class StereoOptions:
    """Settings of :func:`stereo_depths` (defaults: what measured best on fern and DTU, stereo.md)."""

    pairs: int = 4
    """Neighbours matched against each view; the pixel's depth is voted on across these pairs."""
    min_axis_angle: float = 30.0
    """Skip neighbours whose baseline lies within this many degrees of the view's optical axis (a
    baseline along the axis gives no disparity)."""
    max_view_angle: float = 60.0
    """Skip neighbours whose optical axis differs from the view's by more than this many degrees."""
    block_size: int = 5
    """SGBM matching block side in pixels (odd, 1-11)."""
    p1: int = 600
    """SGBM smoothness penalty for disparity changes of one pixel (8 x channels x block_size^2)."""
    p2: int = 2400
    """SGBM smoothness penalty for larger disparity changes (must exceed p1)."""
    uniqueness: int = 10
    """SGBM uniqueness ratio in percent: the best cost must beat the second best by this margin."""
    speckle_window: int = 100
    """SGBM speckle filter: regions of at most this many pixels with inconsistent disparity are dropped
    (0 = off)."""
    speckle_range: int = 2
    """SGBM speckle filter: disparity variation (pixels) inside one region."""
    lr_max_diff: int = 1
    """SGBM left-right check: largest allowed difference (whole pixels) between the left and the
    right disparity (-1 = no check)."""
    max_disparities: int = 256
    """Largest disparity search range in pixels (rounded up to a multiple of 16)."""
    agree: float = 0.02
    """Relative depth difference under which two pairs agree on a pixel."""
    need: int = 2
    """Agreeing pairs for full confidence; a pixel only one pair sees keeps confidence 1/need (coverage,
    not precision, is what the whole-image score punishes)."""
    match_side: int = 640
    """Match each rectified pair on a grid whose long side is at least this many pixels (finer than
    photos smaller than that, at most twice as fine; the disparity is read back at the view's own pixels; 0 = the
    photos' own grid): sub-pixel disparity and a block that covers less of a small object or a thin part. On the
    demo scene matching finer cut the stereo outliers on every object and raised the held-out mesh path and the
    F-score; 256 -> 640 raised DTU's held-out mask PSNR and fern's whole image at several times the stereo CPU
    per view (``python -m bench depth_sources``, the ``, match N`` rows; the demo's 128 px stays at 256, the 2x
    cap). 800 scored about the same as 640 at more than the stereo budget of one CPU-second per view on DTU; a 3-px
    block at the photos' grid instead scored lower (BENCHMARKS "Depth sources")."""
    equalize: bool = False
    """Equalise each rectified pair's contrast (CLAHE on its lightness) before matching. On the demo scene
    it raised the outliers on every object; off."""
    confirm: int = 0
    """Multi-view geometric consistency: keep a pixel's depth only when at least this many other views'
    stereo maps agree with it (forward-backward reprojection within ``agree`` and 1 px, up to 8 nearest
    maps; 0 = keep all: the fusion weighs each pixel by that agreement anyway). On the demo scene a quarter of the
    stereo pixels had no other map agreeing and most of those were far off the exact depth, yet with the default
    mesh settings dropping them (``stereo+model`` fills them from the model) lowered the held-out mesh path; off."""

    def check(self) -> None:
        """One-line :class:`InputError` for a bad setting."""
        bad = []
        if not 1 <= self.pairs <= 16:
            bad.append(("pairs", self.pairs, "an integer in 1-16, e.g. 4"))
        if not (math.isfinite(self.min_axis_angle) and 0 <= self.min_axis_angle < 90):
            bad.append(("min_axis_angle", self.min_axis_angle, "degrees in [0, 90), e.g. 30"))
        if not (math.isfinite(self.max_view_angle) and 0 < self.max_view_angle <= 90):
            bad.append(("max_view_angle", self.max_view_angle, "degrees in (0, 90], e.g. 60"))
        if not (1 <= self.block_size <= 11 and self.block_size % 2 == 1):
            bad.append(("block_size", self.block_size, "an odd integer in 1-11, e.g. 5"))
        if not 0 <= self.p1 < self.p2:
            bad.append(("p1/p2", (self.p1, self.p2), "0 <= p1 < p2, e.g. 600 and 2400"))
        if not 0 <= self.uniqueness <= 100:
            bad.append(("uniqueness", self.uniqueness, "a percentage, e.g. 10"))
        if self.speckle_window < 0 or self.speckle_range < 0:
            bad.append(("speckle_window/speckle_range", (self.speckle_window, self.speckle_range), ">= 0, e.g. 100 and 2"))
        if self.lr_max_diff < -1:
            bad.append(("lr_max_diff", self.lr_max_diff, "-1 (off) or a number of pixels, e.g. 1"))
        if not 16 <= self.max_disparities <= 1024:
            bad.append(("max_disparities", self.max_disparities, "16-1024, e.g. 256"))
        if not (math.isfinite(self.agree) and 0 < self.agree < 1):
            bad.append(("agree", self.agree, "a relative difference in (0, 1), e.g. 0.02"))
        if not 1 <= self.need <= 16:
            bad.append(("need", self.need, "an integer in 1-16, e.g. 2"))
        if not 0 <= self.match_side <= 2048:
            bad.append(("match_side", self.match_side, "0 (the photos' grid) or a long side in px up to 2048, e.g. 640"))
        if not 0 <= self.confirm <= 8:
            bad.append(("confirm", self.confirm, "an integer in 0-8, e.g. 1"))
        if bad:
            name, value, fix = bad[0]
            raise InputError(f"stereo option {name} = {value} is out of range", None, f"use {fix}")


# ---------------------------------------------------------------------- neighbours
def stereo_neighbours(cameras: Cameras, views: list[int], options: StereoOptions) -> list[list[int]]:
    """For each of ``views``, up to ``options.pairs`` other views of ``views`` with sideways baselines:
    the baseline at least ``min_axis_angle`` off the optical axis, the axes within ``max_view_angle``,
    ranked by baseline length over its sideways fraction (short, sideways baselines first)."""
    cams = cameras.to(dtype=torch.float64)
    c, z = cams.centers[views], cams.forward[views]  # [V, 3]
    out = []
    cos_axis, cos_view = math.cos(math.radians(options.min_axis_angle)), math.cos(math.radians(options.max_view_angle))
    for a in range(len(views)):
        b = c - c[a]  # [V, 3]
        dist = b.norm(dim=-1)
        along = (b @ z[a]).abs() / dist.clamp_min(1e-12)
        sideways = (1 - along.square()).clamp_min(0).sqrt()
        ok = (dist > 1e-9) & (along < cos_axis) & (z @ z[a] > cos_view)
        score = torch.where(ok, dist / sideways.clamp_min(1e-6), torch.full_like(dist, math.inf))
        order = torch.argsort(score)
        out.append([views[int(j)] for j in order[: options.pairs] if math.isfinite(float(score[j]))])
    return out


# ---------------------------------------------------------------------- rectification
@dataclass
class Rectified:
    """A pair rectified from known poses: both images seen by cameras with rotation ``R`` (columns: the
    x axis along the baseline, y, z), one focal length ``f`` and principal point ``(cx, cy)``; the right
    camera sits ``baseline`` along x from the left one."""

    R: np.ndarray
    """Rectified camera-to-world rotation. ``# [3, 3]``"""
    f: float
    cx: float
    cy: float
    width: int
    height: int
    baseline: float
    left: int
    """Which of the pair (0 or 1) is the left camera."""

    def pixels_of(self, cam: Cameras, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Where each rectified pixel centre falls in ``cam``'s image (OpenCV's integer-centred
        coordinates, for ``cv2.remap``), on a canvas whose principal point is ``offset`` px right of ``cx``
        (a point of disparity ``d`` then sits ``d - offset`` px from its place on the other canvas).
        ``# [Hr, Wr]`` each, float32"""
        v, u = np.mgrid[0:self.height, 0:self.width].astype(np.float64) + 0.5
        d = np.stack([(u - self.cx - offset) / self.f, (v - self.cy) / self.f, np.ones_like(u)], -1) @ self.R.T  # world
        dc = d @ cam.R[0].numpy()  # camera frame: R^T d
        z = np.where(dc[..., 2] > 1e-9, dc[..., 2], np.nan)
        x = float(cam.fx[0]) * dc[..., 0] / z + float(cam.cx[0]) - 0.5
        y = float(cam.fy[0]) * dc[..., 1] / z + float(cam.cy[0]) - 0.5
        return np.nan_to_num(x, nan=-1e4).astype(np.float32), np.nan_to_num(y, nan=-1e4).astype(np.float32)


def rectify_pair(a: Cameras, b: Cameras, max_scale: float = 1.25, upscale: float = 1.0) -> Rectified:
    """The rectification of cameras ``a`` and ``b`` (one each) from their poses. The left camera is the
    one the baseline leaves along its own +x; the rectified image covers ``a``'s image (whose depth is
    wanted), at most ``max_scale`` times its size, with ``upscale`` times its pixel density."""
    a, b = a.to(dtype=torch.float64), b.to(dtype=torch.float64)
    ca, cb = a.centers[0].numpy(), b.centers[0].numpy()
    base = cb - ca
    B = float(np.linalg.norm(base))
    x = base / B
    left = 0
    if x @ a.R[0, :, 0].numpy() < 0:  # b lies to a's left: b is the left camera
        x, left = -x, 1
    zavg = a.forward[0].numpy() + b.forward[0].numpy()
    z = zavg - (zavg @ x) * x
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    R = np.stack([x, y, z], 1)
    f = upscale * float(np.mean([float(a.fx[0]), float(a.fy[0]), float(b.fx[0]), float(b.fy[0])]))
    W, H = upscale * a.width, upscale * a.height
    corners = []
    for cam in (a,):
        uv = np.array([[0, 0], [cam.width, 0], [0, cam.height], [cam.width, cam.height]], dtype=np.float64)
        d = np.stack([(uv[:, 0] - float(cam.cx[0])) / float(cam.fx[0]), (uv[:, 1] - float(cam.cy[0])) / float(cam.fy[0]),
                      np.ones(4)], -1) @ cam.R[0].numpy().T @ R  # rectified frame
        d = d[d[:, 2] > 1e-3]
        corners.append(f * d[:, :2] / d[:, 2:])
    pts = np.concatenate(corners)
    lo = np.maximum(pts.min(0), [-max_scale * W / 2, -max_scale * H / 2])
    hi = np.minimum(pts.max(0), [max_scale * W / 2, max_scale * H / 2])
    width, height = int(math.ceil(hi[0] - lo[0])), int(math.ceil(hi[1] - lo[1]))
    return Rectified(R, f, float(-lo[0]), float(-lo[1]), max(width, 16), max(height, 16), B, left)


def disparity_range(rect: Rectified, left_center: np.ndarray, bounds: Tensor, options: StereoOptions,
                    view: Cameras | None = None) -> tuple[int, int]:
    """``(minDisparity, numDisparities)`` for the depth range of the ``bounds`` box, or of the part ``view`` sees: where
    a 17x17 grid of ``view``'s pixel rays, image border included, enters and leaves it (else the box's corners)."""
    lo, hi = bounds.double().numpy()
    pts = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    if view is not None:
        v, u = np.meshgrid(np.linspace(0, view.height, 17), np.linspace(0, view.width, 17), indexing="ij")
        d = np.stack([(u.ravel() - float(view.cx[0])) / float(view.fx[0]),
                      (v.ravel() - float(view.cy[0])) / float(view.fy[0]), np.ones(u.size)], -1) @ view.R[0].numpy().T
        o = view.centers[0].numpy()
        with np.errstate(divide="ignore", invalid="ignore"):  # slab test: the ray's segment inside the box
            t0, t1 = (lo - o) / d, (hi - o) / d  # [R, 3]
        enter = np.nanmax(np.maximum(np.minimum(t0, t1), 0.0), -1)
        leave = np.nanmin(np.maximum(t0, t1), -1)
        hit = np.isfinite(enter) & np.isfinite(leave) & (leave > enter)
        if hit.any():
            pts = np.concatenate([o + enter[hit, None] * d[hit], o + leave[hit, None] * d[hit]])
    depth = (pts - left_center) @ rect.R[:, 2]
    far = max(float(depth.max()), 1e-6)
    near = max(float(depth.min()), far * 1e-3)
    dmin = int(math.floor(rect.f * rect.baseline / far))
    dmax = int(math.ceil(rect.f * rect.baseline / near)) + 1
    num = int(min(16 * math.ceil(max(dmax - dmin, 16) / 16), 16 * math.ceil(options.max_disparities / 16)))
    return max(dmin - 1, 0), num


def match(left: np.ndarray, right: np.ndarray, dmin: int, num: int, options: StereoOptions) -> np.ndarray:
    """SGBM disparity of ``left`` against ``right`` (uint8 ``# [H, W, 3]`` each, rectified), NaN where
    unmatched; both are padded on the left by the search range first. ``# [H, W]`` float32"""
    import cv2

    pad = dmin + num
    sgbm = cv2.StereoSGBM_create(minDisparity=dmin, numDisparities=num, blockSize=options.block_size, P1=options.p1,
                                 P2=options.p2, disp12MaxDiff=options.lr_max_diff, preFilterCap=63,
                                 uniquenessRatio=options.uniqueness, speckleWindowSize=options.speckle_window,
                                 speckleRange=options.speckle_range, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    L = cv2.copyMakeBorder(left, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
    R = cv2.copyMakeBorder(right, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
    disp = sgbm.compute(L, R)[:, pad:].astype(np.float32) / 16.0
    disp[disp < dmin] = np.nan
    return disp


def equalized(images: list[np.ndarray]) -> list[np.ndarray]:
    """``images`` (uint8 RGB) with the lightness of each equalised by CLAHE (OpenCV, 8x8 tiles)."""
    import cv2

    clahe = cv2.createCLAHE(clipLimit=3.0, tileGridSize=(8, 8))
    out = []
    for img in images:
        lab = cv2.cvtColor(img, cv2.COLOR_RGB2LAB)
        lab[..., 0] = clahe.apply(np.ascontiguousarray(lab[..., 0]))
        out.append(cv2.cvtColor(lab, cv2.COLOR_LAB2RGB))
    return out


def _uint8(image: Tensor) -> np.ndarray:
    return (image.detach().float().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def pair_depth(images: Tensor, cameras: Cameras, i: int, j: int, bounds: Tensor, options: StereoOptions) -> np.ndarray:
    """z-depth of view ``i`` from the pair ``(i, j)``, NaN where unmatched. ``# [H, W]`` float32"""
    import cv2

    ci, cj = cameras[i].to(dtype=torch.float64), cameras[j].to(dtype=torch.float64)
    rect = rectify_pair(ci, cj, upscale=float(np.clip(options.match_side / max(ci.width, ci.height), 1.0, 2.0)))
    left_cam = ci if rect.left == 0 else cj
    dmin, num = disparity_range(rect, left_cam.centers[0].numpy(), bounds, options, ci)
    # the other image's canvas moves by dmin (right of the left one's when i is left, else left of it)
    imgs = [cv2.remap(_uint8(images[k]), *rect.pixels_of(cam, offset), cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            for cam, k, offset in ((ci, i, 0.0), (cj, j, dmin if rect.left == 0 else -dmin))]
    if options.equalize:
        imgs = equalized(imgs)
    if rect.left == 0:  # i is the left image
        disp = match(imgs[0], imgs[1], 0, num, options)
    else:  # i is the right image: match the mirrored pair, mirror back
        disp = match(imgs[0][:, ::-1].copy(), imgs[1][:, ::-1].copy(), 0, num, options)[:, ::-1]
    disp = disp + dmin  # [Hr, Wr] the disparity between the unshifted canvases
    # read the disparity back at view i's pixels
    H, W = ci.height, ci.width
    v, u = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    ray = np.stack([(u - float(ci.cx[0])) / float(ci.fx[0]), (v - float(ci.cy[0])) / float(ci.fy[0]), np.ones_like(u)], -1)
    d = ray @ ci.R[0].numpy().T @ rect.R  # rectified frame, camera-z of ray = 1
    dz = d[..., 2]
    ur = rect.f * d[..., 0] / np.maximum(dz, 1e-9) + rect.cx - 0.5
    vr = rect.f * d[..., 1] / np.maximum(dz, 1e-9) + rect.cy - 0.5
    disp_i = bilinear_valid(disp, ur, vr)
    with np.errstate(divide="ignore", invalid="ignore"):
        z_rect = rect.f * rect.baseline / disp_i
        depth = z_rect / dz
    depth[~(np.isfinite(depth) & (depth > 0) & (dz > 1e-6))] = np.nan
    return depth.astype(np.float32)


def bilinear_valid(img: np.ndarray, x: np.ndarray, y: np.ndarray, edge: float = 1.0) -> np.ndarray:
    """``img # [H, W]`` (NaN = none) at float coordinates (integer-centred): bilinear where the four
    neighbours are valid and within ``edge`` of each other, else the nearest pixel, NaN outside."""
    H, W = img.shape
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 < W - 1) & (y0 < H - 1)
    x0c, y0c = np.clip(x0, 0, W - 2), np.clip(y0, 0, H - 2)
    fx, fy = x - x0c, y - y0c
    a, b = img[y0c, x0c], img[y0c, x0c + 1]
    c, d = img[y0c + 1, x0c], img[y0c + 1, x0c + 1]
    stack = np.stack([a, b, c, d])
    finite = np.isfinite(stack).all(0)
    filled = np.where(np.isfinite(stack), stack, 0.0)
    smooth = finite & (filled.max(0) - filled.min(0) <= edge)
    bil = (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy
    xn = np.clip(np.round(x).astype(np.int64), 0, W - 1)
    yn = np.clip(np.round(y).astype(np.int64), 0, H - 1)
    out = np.where(smooth, bil, img[yn, xn])
    out[~inside] = np.nan
    return out


# ---------------------------------------------------------------------- voting
def vote(depths: np.ndarray, agree: float, need: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Combine ``depths # [K, H, W]`` (NaN = none) of one view from ``K`` pairs: each pixel keeps the mean
    of the depths that agree (within ``agree`` relative) with the best-supported one.

    Returns depth (0 = none), confidence ``min(1, support / need)`` and the support (pairs that agree).
    ``# [H, W]`` each."""
    K = depths.shape[0]
    valid = np.isfinite(depths)
    d = np.where(valid, depths, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        close = (np.abs(d[:, None] - d[None]) <= agree * d[None]) & valid[:, None] & valid[None]  # [K, K, H, W]: j agrees with k
    support = close.sum(0)  # [K, H, W] support of each k
    best = support.argmax(0)  # [H, W]
    agree_best = np.take_along_axis(close, best[None, None].repeat(K, 0), 1)[:, 0]  # [K, H, W]
    n = agree_best.sum(0)
    depth = np.where(n > 0, (d * agree_best).sum(0) / np.maximum(n, 1), 0.0)
    conf = np.minimum(1.0, n / max(1, min(need, K)))
    return depth.astype(np.float32), conf.astype(np.float32), n


def unconfirmed(cameras: Cameras, depths: Tensor, rel: float, need: int) -> Tensor:
    """Pixels of the depth maps ``depths # [N, H, W]`` (at ``cameras``) with a depth that fewer than ``need``
    of the other maps confirm (:func:`omnirecon.mesh.fusion.consistency`: forward-backward reprojection
    within ``rel`` and 1 px, 8 nearest maps). ``# [N, H, W]`` bool"""
    from omnirecon.mesh.fusion import consistency

    return (consistency(cameras, depths, rel=rel) < need) & (depths > 0)


def stereo_depths(images: Tensor, cameras: Cameras, views: list[int], bounds: Tensor,
                  options: StereoOptions | None = None, on_view=None) -> dict:
    """Classical stereo depth at each of ``views`` from its :func:`stereo_neighbours` among ``views``.

    Args:
        images: RGB in [0, 1] of every view of the scene. ``# [N, H, W, 3]``
        cameras: The scene's ``N`` cameras.
        views: Views to compute depth at (and to match against).
        bounds: ``[min, max]`` of the content; sets the disparity search range. ``# [2, 3]``
        on_view: Called after each view (progress bars).

    Returns:
        ``depth`` (z-depth, 0 = none) and ``confidence`` in [0, 1] at ``cameras[views]`` (``# [V, H, W]``),
        ``pairs`` (the neighbours of each view), ``options`` and ``unconfirmed_dropped`` (the fraction of
        the voted depths no other view confirmed, dropped; ``StereoOptions.confirm``).
    """
    options = options or StereoOptions()
    options.check()
    views = list(views)
    neighbours = stereo_neighbours(cameras, views, options)
    depths, confs = [], []
    H, W = cameras.height, cameras.width
    for i, near in zip(views, neighbours):
        per_pair = [pair_depth(images, cameras, i, j, bounds, options) for j in near]
        if per_pair:
            d, c, _ = vote(np.stack(per_pair), options.agree, options.need)
        else:
            d, c = np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)
        depths.append(torch.from_numpy(d))
        confs.append(torch.from_numpy(c))
        if on_view is not None:
            on_view()
    depth, conf = torch.stack(depths), torch.stack(confs)
    dropped = 0.0
    if options.confirm > 0 and len(views) > 1:  # multi-view geometric consistency
        lone = unconfirmed(cameras[views], depth, options.agree, options.confirm)
        dropped = float(lone.sum() / max(1, int((depth > 0).sum())))
        depth, conf = depth.masked_fill(lone, 0.0), conf.masked_fill(lone, 0.0)
    return {"depth": depth, "confidence": conf, "pairs": neighbours, "options": asdict(options),
            "unconfirmed_dropped": dropped}
