"""Geometry metrics: Chamfer / F-score, depth errors, silhouettes and the mesh picture."""

import math

import numpy as np
import pytest
import torch
import trimesh

from omnirecon.cameras import Cameras, look_at
from omnirecon.data.scene import Scene
from omnirecon.mesh import geometry


def grid_plane(n: int = 40, size: float = 2.0, z: float = 0.0) -> trimesh.Trimesh:
    """A square ``size`` wide in the plane ``z``, as ``2 n^2`` triangles."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    verts = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], -1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])
    return trimesh.Trimesh(verts, faces, process=False)


def camera_looking_down(height: float = 3.0, res: int = 32, f: float = 40.0) -> Cameras:
    c2w = look_at(torch.tensor([[0, 0, height]], dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                  torch.tensor([0, 1.0, 0], dtype=torch.float64))
    return Cameras(torch.tensor([f]), torch.tensor([f]), res / 2, res / 2, c2w, res, res)


def test_chamfer_self_shift_and_fscore():
    plane = grid_plane()
    same = geometry.mesh_chamfer(plane, plane, threshold=0.05, count=20_000)  # sample spacing ~0.014
    assert same["chamfer"] < 0.01 and same["fscore"] == 1.0  # two independent samplings of one surface
    exact = geometry.chamfer_fscore(geometry.sample_points(plane, 5000), geometry.sample_points(plane, 5000), 0.01)
    assert exact["chamfer"] == 0 and exact["fscore"] == 1.0  # identical point sets
    shifted = grid_plane(z=0.1)
    r = geometry.mesh_chamfer(plane, shifted, threshold=0.01, count=20_000)
    assert r["accuracy"] == pytest.approx(0.1, rel=0.03) and r["completeness"] == pytest.approx(0.1, rel=0.03)
    assert r["chamfer"] == pytest.approx(0.1, rel=0.03) and r["fscore"] == 0.0
    big = trimesh.creation.icosphere(4, radius=1.0)
    r = geometry.mesh_chamfer(big, big.copy().apply_translation([0, 0, 5.0]), threshold=0.05, count=5000)
    assert r["fscore"] == 0.0 and r["chamfer"] > 2
    capped = geometry.mesh_chamfer(plane, shifted, threshold=0.01, max_dist=0.05, count=5000)
    assert capped["accuracy_dropped"] == 1.0 and math.isinf(capped["chamfer"])  # DTU drops, not clips


def test_sample_points_uniform_by_area():
    tris = trimesh.Trimesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [10, 0, 0], [13, 0, 0], [10, 1, 0.0]]),
                           np.array([[0, 1, 2], [3, 4, 5]]), process=False)
    pts = geometry.sample_points(tris, 40_000, seed=1)
    share = (pts[:, 0] >= 10).mean()
    assert share == pytest.approx(0.75, abs=0.01)  # areas 0.5 and 1.5
    assert (pts[:, 2] == 0).all()
    assert (geometry.sample_points(tris, 10, seed=3) == geometry.sample_points(tris, 10, seed=3)).all()


def test_depth_errors_and_iou():
    gt = np.array([[1.0, 2.0], [4.0, 0.0]])
    pred = np.array([[1.1, 2.0], [0.0, 3.0]])
    e = geometry.depth_errors(pred, gt)
    assert e["abs_rel"] == pytest.approx(0.05) and e["rmse"] == pytest.approx(math.sqrt(0.01 / 2))
    assert e["delta1"] == 1.0 and e["coverage"] == pytest.approx(2 / 3)
    assert geometry.mask_iou([[1, 1], [0, 0]], [[1, 0], [1, 0]]) == pytest.approx(1 / 3)
    assert geometry.mask_iou(np.zeros((2, 2)), np.zeros((2, 2))) == 1.0


def test_silhouette_depth_and_picture_of_a_square():
    cam = camera_looking_down()
    square = grid_plane(4, 1.0)  # 1 x 1 at distance 3: 40 / 3 = 13.3 px wide, centred
    sil = geometry.silhouette(square, cam)
    assert sil.sum() == pytest.approx((40 / 3) ** 2, rel=0.15)
    assert sil[16, 16] and not sil[0, 0]
    flipped = trimesh.Trimesh(square.vertices, square.faces[:, ::-1], process=False)
    assert (geometry.silhouette(flipped, cam) == sil).all()  # both sides are drawn
    depth = geometry.mesh_depth(square, cam)
    assert np.allclose(depth[sil], 3.0) and (depth[~sil] == 0).all()
    img = geometry.shaded_image(square, cam)
    assert img.shape == (32, 32, 3) and img.dtype == np.uint8
    assert (img[0, 0] == 255).all() and img[16, 16].max() < 255  # white background, shaded square
    behind = geometry.silhouette(square.copy().apply_translation([0, 0, 5.0]), cam)  # behind the camera
    assert not behind.any()


def test_observed_points_use_gt_depth():
    cam = camera_looking_down(res=32)
    square = grid_plane(4, 1.0)
    depth = torch.from_numpy(geometry.mesh_depth(square, cam)).float()[None]
    scene = Scene(torch.zeros(1, 32, 32, 3), cam, torch.ones(1), torch.full((1,), 9.0),
                  torch.tensor([[-1.0] * 3, [1.0] * 3]), {}, depths=depth)
    pts = np.array([[0.1, 0.1, 0.0], [0.1, 0.1, -0.5], [0.9, 0.9, 0.0]])  # on, under, off it
    assert geometry.observed(pts, scene).tolist() == [True, False, False]
