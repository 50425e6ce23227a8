"""Exact z-buffer rasterizer of a triangle soup (NumPy, float64): a visibility buffer.

The rasterizer finds, for every sample point of the image, the nearest triangle whose projection
covers it, with the perspective-correct barycentrics of the hit: a visibility buffer. Depth is
``1 / (sum_k b_k / z_k)``, which is exact for a planar triangle (``1/z`` is affine in the image),
so the depth and positions written out lie on the exported mesh up to float64 rounding.

Work per view is proportional to the number of triangles plus the pixels their bounding boxes
cover: each triangle's bounding box is expanded into candidate samples, the samples inside all
three edges are kept, and the nearest one per sample wins (``np.minimum.at``; ties go to the
lower triangle index, so the result is deterministic).

It renders the procedural scenes (:mod:`omnirecon.data.synth.render` shades its fragments), is the test
oracle of the fast rasterizer (:mod:`omnirecon.render.raster`) and draws meshes for scoring
(:mod:`omnirecon.mesh.geometry`). Tensors (arrays) in, arrays out; no network.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Fragments:
    """Visibility buffer of one view: nearest triangle per sample."""

    face: np.ndarray
    """Triangle index, -1 where nothing is hit. ``# [H, W]`` int64"""
    bary: np.ndarray
    """Perspective-correct barycentrics (sum to 1). ``# [H, W, 3]`` float64"""
    depth: np.ndarray
    """Camera-frame z of the hit, 0 where nothing is hit. ``# [H, W]`` float64"""


def rasterize(
    vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, w2c: np.ndarray, width: int, height: int,
    near: float = 1e-6, max_candidates: int = 1 << 21,
) -> Fragments:
    """Visibility buffer of a triangle mesh seen by one pinhole camera (OpenCV frame).

    Samples sit at pixel centres ``(j + 0.5, i + 0.5)``; render at ``s`` samples per pixel side by
    scaling ``K`` (``fx, fy, cx, cy`` times ``s``) and the size. Back faces (normal pointing away
    from the camera) are skipped, so meshes must be closed and outward-facing, or one-sided
    surfaces seen from their front (the ground).

    Args:
        vertices: World positions. ``# [V, 3]`` float64
        faces: ``# [F, 3]`` int
        K: Intrinsics. ``# [3, 3]``
        w2c: World-to-camera rigid transform. ``# [4, 4]``
        width, height: Image size in samples.
        near: Every vertex must lie at camera z > ``near`` (the generator keeps content in front of
            all cameras; nothing is clipped here).
        max_candidates: Candidate samples expanded at once (memory: ~150 bytes each); the result does not
            depend on it.
    """
    cam = vertices @ w2c[:3, :3].T + w2c[:3, 3]  # [V, 3]
    z = cam[:, 2]
    if z.min() <= near:
        raise ValueError("a vertex lies behind the camera; the scene layout must keep content in front")
    uv = cam[:, :2] / z[:, None] * K[[0, 1], [0, 1]] + K[[0, 1], [2, 2]]  # [V, 2]
    tri = uv[faces]  # [F, 3, 2]
    tz = z[faces]  # [F, 3]
    # Front faces: geometric normal towards the camera (camera centre is the origin of `cam`).
    p0 = cam[faces[:, 0]]
    normal = np.cross(cam[faces[:, 1]] - p0, cam[faces[:, 2]] - p0)  # [F, 3]
    front = np.einsum("fc,fc->f", normal, p0) < 0
    u, v = tri[..., 0], tri[..., 1]  # [F, 3] each
    j0 = np.maximum(np.ceil(np.minimum(np.minimum(u[:, 0], u[:, 1]), u[:, 2]) - 0.5), 0).astype(np.int64)  # [F]
    j1 = np.minimum(np.floor(np.maximum(np.maximum(u[:, 0], u[:, 1]), u[:, 2]) - 0.5), width - 1).astype(np.int64)
    i0 = np.maximum(np.ceil(np.minimum(np.minimum(v[:, 0], v[:, 1]), v[:, 2]) - 0.5), 0).astype(np.int64)
    i1 = np.minimum(np.floor(np.maximum(np.maximum(v[:, 0], v[:, 1]), v[:, 2]) - 0.5), height - 1).astype(np.int64)
    nx, ny = j1 - j0 + 1, i1 - i0 + 1
    area = _edge(tri[:, 0], tri[:, 1], tri[:, 2])  # [F], 2x signed area in the image
    keep = np.flatnonzero(front & (nx > 0) & (ny > 0) & (np.abs(area) > 1e-12))

    # Barycentrics are affine in (u, v): b_k = A[f, k] . (u, v, 1).
    t = tri[keep]
    A = np.empty((len(keep), 3, 3))
    for k in range(3):
        a, b = t[:, (k + 1) % 3], t[:, (k + 2) % 3]  # edge opposite vertex k
        A[:, k, 0] = -(b[:, 1] - a[:, 1])
        A[:, k, 1] = b[:, 0] - a[:, 0]
        A[:, k, 2] = (b[:, 1] - a[:, 1]) * a[:, 0] - (b[:, 0] - a[:, 0]) * a[:, 1]
    A /= area[keep][:, None, None]

    # Expand every bounding box into candidate samples and keep those inside all three edges, a run of
    # triangles at a time (at most `max_candidates` samples, a triangle larger than that alone): the memory is
    # ~150 bytes per candidate, and a mesh's large triangles (a backdrop, long fills) reached 6 GB in one go.
    counts = (nx * ny)[keep]
    zbuf = np.full(width * height, np.inf)  # nearest depth so far
    face_k = np.full(width * height, -1, dtype=np.int64)  # its triangle (index into keep)
    bary_out = np.zeros((width * height, 3))
    ends = np.cumsum(counts)
    start = 0
    while start < len(keep):
        stop = max(start + 1, int(np.searchsorted(ends, (ends[start - 1] if start else 0) + max_candidates, "right")))
        sl = np.arange(start, stop)
        owner = np.repeat(sl, counts[sl])  # [C] index into keep
        offset = np.arange(len(owner)) - np.repeat(np.cumsum(counts[sl]) - counts[sl], counts[sl])
        width_k = nx[keep][owner]
        col = j0[keep][owner] + offset % width_k
        row = i0[keep][owner] + offset // width_k
        M = A[owner]  # [C, 3, 3]
        bary = M[:, :, 0] * (col[:, None] + 0.5) + M[:, :, 1] * (row[:, None] + 0.5) + M[:, :, 2]  # [C, 3]
        inside = np.flatnonzero((bary[:, 0] >= -1e-10) & (bary[:, 1] >= -1e-10) & (bary[:, 2] >= -1e-10))
        owner, bary = owner[inside], bary[inside]
        pix = row[inside] * width + col[inside]
        inv_z = bary / tz[keep[owner]]  # [S, 3]; 1/z is affine in the image too
        depth = 1.0 / (inv_z[:, 0] + inv_z[:, 1] + inv_z[:, 2])
        # Z-buffer of this run: nearest depth per sample, ties to the lowest triangle index; it replaces the
        # earlier runs' (lower indices) only where strictly nearer, so ties still go to the lowest index.
        zrun = np.full(width * height, np.inf)
        np.minimum.at(zrun, pix, depth)
        win = np.flatnonzero(depth == zrun[pix])
        first = np.full(width * height, np.iinfo(np.int64).max)
        np.minimum.at(first, pix[win], win)
        hit = np.flatnonzero((first < np.iinfo(np.int64).max) & (zrun < zbuf))
        best = first[hit]
        zbuf[hit] = depth[best]
        face_k[hit] = owner[best]
        bary_out[hit] = inv_z[best] * depth[best][:, None]  # perspective-correct
        start = stop
    hit = np.flatnonzero(face_k >= 0)

    face = np.full(width * height, -1, dtype=np.int64)
    face[hit] = keep[face_k[hit]]
    zout = np.zeros(width * height)
    zout[hit] = zbuf[hit]
    return Fragments(face.reshape(height, width), bary_out.reshape(height, width, 3), zout.reshape(height, width))


def _edge(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Edge function ``(b - a) x (p - a)`` of 2D points. ``# [...]``"""
    return (b[..., 0] - a[..., 0]) * (p[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (p[..., 0] - a[..., 0])
