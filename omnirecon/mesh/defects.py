"""What a user sees away from the photos, counted without ground truth: the share of a frame's pixels drawn by
faces that no photo supports.

A face is a *defect* of one of three kinds:

* **fill**: one of completion's fills (:mod:`omnirecon.mesh.complete`): a surface made to cover some view's
  pixels from that view's own depth alone. The pipeline writes the fused surface's faces first, so the fills are
  the faces from ``fill_from`` on (``MeshResult.info["completion"]["surface_faces"]``).
* **unseen**: no training view sees the face within :data:`MAX_ANGLE` degrees of its normal: in every view the face
  is hidden behind other surface (a depth test of its centroid against the view's rasterized depth, both sides of
  every face drawn), outside the image, or seen only edge-on or from behind.
* **small**: the face belongs to a connected piece whose extent (bounding-box diagonal) is under :data:`MIN_PIECE`
  of the scene bounds' diagonal: the shards and fragments that inconsistent depth leaves.

:class:`DefectCounter` rasterizes a frame's face ids as the mesh path draws it (back faces culled) and returns the
share of the frame's pixels each kind draws (``any``: drawn by a defect face of any kind). Pixels no face covers are
not defects here: the renderer's fill shades them, and coverage counts them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from omnirecon.cameras import Cameras

MAX_ANGLE = 75.0
"""Degrees between a face's normal and the direction to a training camera beyond which that view does not count as
seeing the face."""
MIN_PIECE = 0.05
"""A connected piece whose bounding-box diagonal is under this fraction of the scene bounds' diagonal is a fragment."""
KINDS = ("fill", "unseen", "small")
"""The kinds of defect face, in the order :meth:`DefectFaces.codes` numbers them (bit 0, 1, 2)."""


@dataclass
class DefectFaces:
    """Per face of a mesh: whether it is a defect of each kind (module docstring). Each ``# [F]`` bool."""

    fill: np.ndarray
    unseen: np.ndarray
    small: np.ndarray

    @property
    def any(self) -> np.ndarray:
        """A defect of any kind. ``# [F]`` bool"""
        return self.fill | self.unseen | self.small

    def codes(self) -> np.ndarray:
        """The kinds as bits (fill 1, unseen 2, small 4). ``# [F]`` uint8"""
        return (self.fill.astype(np.uint8) | (self.unseen.astype(np.uint8) << 1) | (self.small.astype(np.uint8) << 2))

    def counts(self) -> dict[str, int]:
        """Faces of each kind and of any kind."""
        return {**{k: int(getattr(self, k).sum()) for k in KINDS}, "any": int(self.any.sum()), "faces": len(self.fill)}


def small_pieces(mesh: trimesh.Trimesh, size: float) -> np.ndarray:
    """Faces of connected pieces (shared edges) whose bounding-box diagonal is under ``size``. ``# [F]`` bool"""
    F = len(mesh.faces)
    if F == 0:
        return np.zeros(0, bool)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=F)  # [F]
    corners = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]  # [F, 3, 3]
    n = int(labels.max()) + 1
    lo = np.full((n, 3), np.inf)
    hi = np.full((n, 3), -np.inf)
    np.minimum.at(lo, labels, corners.min(1))
    np.maximum.at(hi, labels, corners.max(1))
    return (np.linalg.norm(hi - lo, axis=1) < size)[labels]


def seen_faces(mesh: trimesh.Trimesh, cameras: Cameras, max_angle: float = MAX_ANGLE, tol: float = 0.01) -> np.ndarray:
    """Faces some of ``cameras`` sees within ``max_angle`` degrees of the face's normal: the face's centroid projects
    into the view's image, in front, no farther than ``1 + tol`` times the largest rasterized depth of the 2x2 pixel
    centres around it (both sides of every face drawn: :func:`omnirecon.mesh.kernel.unoccluded`'s one-sided test, which
    holds on the face's own surface however small the face is), and the direction to the camera lies within
    ``max_angle`` of the normal. ``# [F]`` bool"""
    from omnirecon.mesh.kernel import block_depth_max, unoccluded
    from omnirecon.render.raster import MeshRasterizer

    F = len(mesh.faces)
    seen = torch.zeros(F, dtype=torch.bool)
    if F == 0:
        return seen.numpy()
    cams = cameras.to(dtype=torch.float64)
    normals = torch.from_numpy(np.array(mesh.face_normals, np.float64))  # [F, 3]
    centroids = torch.from_numpy(np.array(mesh.triangles_center, np.float64))  # [F, 3]
    cos_max = float(np.cos(np.radians(max_angle)))
    with MeshRasterizer.from_trimesh(mesh, cull_back_faces=False) as rast:
        for i in range(len(cams)):
            p = cams[i].project(centroids)
            to_cam = cams.centers[i] - centroids  # [F, 3]
            facing = (normals * to_cam).sum(1) >= cos_max * to_cam.norm(dim=1)
            dmax = block_depth_max(rast.depth(cams[i]).double()[None])  # [1, H + 1, W + 1]
            front = unoccluded(dmax, p.uv[0].T[None], p.depth[0][None], tol)[0]
            seen |= p.in_image[0] & (p.depth[0] > 0) & facing & front
    return seen.numpy()


def defect_faces(mesh: trimesh.Trimesh, cameras: Cameras, bounds: torch.Tensor, fill_from: int | None = None,
                 max_angle: float = MAX_ANGLE, min_piece: float = MIN_PIECE) -> DefectFaces:
    """The defect faces of ``mesh`` (scene frame) made from the training views ``cameras`` in a scene of ``bounds
    # [2, 3]``; completion's fills are the faces from ``fill_from`` on (``None``: no fills)."""
    F = len(mesh.faces)
    fill = np.zeros(F, bool)
    if fill_from is not None:
        fill[int(fill_from):] = True
    diag = float((bounds[1] - bounds[0]).double().norm())
    return DefectFaces(fill, ~seen_faces(mesh, cameras, max_angle), small_pieces(mesh, min_piece * diag))


def pixel_shares(face_ids: np.ndarray, faces: DefectFaces) -> dict[str, float]:
    """Share of a frame's pixels (``face_ids # [H, W]``, -1 = none) drawn by each kind of defect face, by any kind,
    and covered at all."""
    hit = face_ids >= 0
    f = face_ids[hit]
    n = face_ids.size
    out = {k: float(getattr(faces, k)[f].sum()) / n for k in KINDS}
    out["any"] = float(faces.any[f].sum()) / n
    out["covered"] = float(hit.sum()) / n
    return out


class DefectCounter:
    """Defect shares of any frame of one mesh: :func:`defect_faces` once, then each frame's face ids rasterized as
    the mesh path draws them (back faces culled). Use as a context manager (frees the rasterizer)."""

    def __init__(self, mesh: trimesh.Trimesh, cameras: Cameras, bounds: torch.Tensor, fill_from: int | None = None,
                 cull_back_faces: bool = True):
        from omnirecon.render.raster import MeshRasterizer

        self.faces = defect_faces(mesh, cameras, bounds, fill_from)
        self.rasterizer = MeshRasterizer.from_trimesh(mesh, cull_back_faces=cull_back_faces)

    def face_ids(self, camera: Cameras) -> np.ndarray:
        """The face drawn at each pixel of ``camera`` (-1 = none). ``# [H, W]`` int64"""
        return self.rasterizer.face_ids(camera)

    def __call__(self, camera: Cameras) -> dict[str, float]:
        """:func:`pixel_shares` of ``camera``'s frame."""
        return pixel_shares(self.face_ids(camera), self.faces)

    def picture(self, camera: Cameras) -> np.ndarray:
        """The frame's defect pixels coloured by kind (fill red, unseen blue, small yellow; a mix of kinds white),
        other covered pixels grey, uncovered black. ``# [H, W, 3]`` uint8"""
        ids = self.face_ids(camera)
        codes = np.where(ids >= 0, self.faces.codes()[ids.clip(0)].astype(np.int64) + 1, 0)
        palette = np.array([[0, 0, 0], [96, 96, 96], [230, 40, 40], [40, 90, 230], [255, 255, 255], [240, 210, 40],
                            [255, 255, 255], [255, 255, 255], [255, 255, 255]], np.uint8)
        return palette[codes]

    def close(self) -> None:
        self.rasterizer.close()

    def __enter__(self) -> DefectCounter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
