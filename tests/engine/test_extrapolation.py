"""Away from the photos (issue 42): the path a user watches, walks, COLMAP bounds that hold what the photos see, and
frames scored against a procedural scene's exact images."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from omnirecon.cameras import Cameras, closest_point_to_axes, look_at
from omnirecon.data.colmap import triangulated
from omnirecon.data.synth.generate import SynthOptions, generate_scene, render_cameras
from omnirecon.engine.extrapolation import PATH_BEYOND, procedural_truth, user_path
from omnirecon.engine.protocols import extrapolation_split
from omnirecon.engine.scenes import load_at_resolution
from omnirecon.trajectory import azimuths, is_walk, nearest_photo_degrees


def test_the_path_reaches_past_the_photos_arc(tmp_path):
    """Photos over one arc of a procedural object scene: the orbit sweeps it and goes 15 degrees past each end."""
    scene = load_at_resolution(generate_scene(tmp_path, 3, SynthOptions(views=48, resolution=16, antialias=1)), 16)
    split = extrapolation_split(scene)
    cams, kind = user_path(scene, split.train, 40)
    assert kind == "orbit"
    center = closest_point_to_axes(scene.cameras[split.train])
    away = nearest_photo_degrees(cams.c2w, scene.cameras[split.train], center)
    assert PATH_BEYOND - 5 < float(away.max()) < PATH_BEYOND + 15  # elevation adds to the azimuth's 15 degrees
    az = torch.rad2deg(azimuths(scene.cameras[split.train], center))  # the first training view at 0
    az = torch.where(az > 180, az - 360, az)
    assert float(az.max() - az.min()) <= 100.5


def walk(n: int = 8) -> Cameras:
    eye = torch.stack([torch.zeros(n), torch.linspace(0, 3.0, n), torch.zeros(n)], -1).double()
    eye[:, 0] = 0.05 * torch.sin(torch.arange(n).double())  # a little sway
    c2w = look_at(eye, eye + torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), torch.tensor([0, 0, 1.0]).double())
    return Cameras(torch.full((n,), 50.0), torch.full((n,), 50.0), 32.0, 24.0, c2w, 64, 48)


def test_a_walk_is_told_from_a_forward_facing_grid():
    grid_eye = torch.tensor([[x, 0.0, z] for x in (-0.3, 0.0, 0.3) for z in (-0.2, 0.2)], dtype=torch.float64)
    c2w = look_at(grid_eye, grid_eye + torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                  torch.tensor([0, 0, 1.0]).double())
    grid = Cameras(torch.full((6,), 50.0), torch.full((6,), 50.0), 32.0, 24.0, c2w, 64, 48)
    assert is_walk(walk()) and not is_walk(grid)


def test_the_default_surface_follows_the_scene_kind():
    """``mesh --surface auto``: the coherent surface on a walk (also one walked out and back, whose converging axes
    make an "object" rig); fusion on a forward-facing grid and on an orbit."""
    from types import SimpleNamespace

    from omnirecon.mesh.build import default_surface
    from omnirecon.workflows.mesh import MeshConfig

    grid_eye = torch.tensor([[x, 0.0, z] for x in (-0.3, 0.0, 0.3) for z in (-0.2, 0.2)], dtype=torch.float64)
    c2w = look_at(grid_eye, grid_eye + torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                  torch.tensor([0, 0, 1.0]).double())
    grid = Cameras(torch.full((6,), 50.0), torch.full((6,), 50.0), 32.0, 24.0, c2w, 64, 48)
    street = SimpleNamespace(rig="forward", cameras=walk())
    assert default_surface(street) == "coherent"
    assert default_surface(SimpleNamespace(rig="forward", cameras=grid)) == "fusion"
    back = walk(16)
    back.c2w[8:, :3, :3] = back.c2w[8:, :3, :3] @ torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))
    back.c2w[8:, 0, 3] += 0.3  # the other pavement, looking back the way it came
    assert is_walk(back) and default_surface(SimpleNamespace(rig="object", cameras=back)) == "coherent"
    ring = torch.tensor([[math.cos(a), math.sin(a), 0.3] for a in torch.linspace(0, 1.75, 12).tolist()],
                        dtype=torch.float64)  # 100 degrees of an orbit, looking at the centre
    orbit = Cameras(torch.full((12,), 50.0), torch.full((12,), 50.0), 32.0, 24.0,
                    look_at(ring, torch.zeros_like(ring), torch.tensor([0, 0, 1.0]).double()), 64, 48)
    assert not is_walk(orbit) and default_surface(SimpleNamespace(rig="object", cameras=orbit)) == "fusion"
    assert default_surface(None) == "fusion"
    assert MeshConfig(scene=Path("s")).mesh_options(street).surface == "coherent"
    assert MeshConfig(scene=Path("s"), surface="fusion").mesh_options(street).surface == "fusion"


def test_triangulated_points_need_two_directions():
    """A point two cameras see 20 degrees apart counts; one seen from a single direction (its rays within half a
    degree, the far end of a street) does not."""
    centers = {1: np.array([0.0, 0.0, 0.0]), 2: np.array([1.0, 0.0, 0.0]), 3: np.array([0.005, 0.0, 0.0])}
    xyz = np.array([[0.5, 0.0, 2.8], [0.0, 0.0, 3.0], [0.0, 0.0, 1e4]])
    tracks = [np.array([[1, 0], [2, 0]]), np.array([[1, 1], [3, 1]]), np.array([[1, 2], [2, 2]])]
    assert triangulated(tracks, centers, xyz).tolist() == [True, False, False]


def test_exact_images_at_any_pose_match_the_generator(tmp_path):
    """render_cameras at a scene's own views reproduces its images (8-bit PNG rounding), and procedural_truth maps a
    loaded scene's cameras back into the file's frame."""
    path = generate_scene(tmp_path, 5, SynthOptions(views=6, resolution=24))
    scene = load_at_resolution(path, 24)
    truth = procedural_truth(path, scene, scene.cameras[[1, 2]])
    assert truth.shape == (2, 24, 24, 3)
    assert float((truth - scene.images[[1, 2]]).abs().max()) < 2.5 / 255
    world = scene.cameras[[3]].transformed(scene.to_input.double())
    again = render_cameras(path, world.c2w.numpy(), world.K[0].numpy(), 24, 24)
    assert np.abs(again[0] - scene.images[3].numpy()).max() < 2.5 / 255
    assert procedural_truth(tmp_path / "nothing", scene, scene.cameras[[1]]) is None


@pytest.mark.parametrize("span", [360.0, 90.0])
def test_extrapolation_split_on_a_ring(span):
    """Cameras on a ring (around, or over a partial arc): training views within one arc, test views 10-30 degrees
    beyond it, none shared."""
    from types import SimpleNamespace

    n = 72
    a = torch.deg2rad(torch.linspace(0, span, n + 1)[:n] if span == 360 else torch.linspace(0, span, n)).double()
    eye = 3 * torch.stack([a.cos(), a.sin(), torch.full_like(a, 0.3)], -1)
    c2w = look_at(eye, torch.zeros(n, 3, dtype=torch.float64), torch.tensor([0, 0, 1.0]).double())
    cams = Cameras(torch.full((n,), 50.0), torch.full((n,), 50.0), 32.0, 32.0, c2w, 64, 64)
    scene = SimpleNamespace(rig="object", cameras=cams, path=None, __len__=lambda: n)
    split = extrapolation_split(scene, list(range(n)))
    assert not set(split.train) & set(split.test) and split.test
    assert split.arc == pytest.approx(100.0 if span == 360 else span - 40.0)
    assert all(10 <= b <= 30 for b in split.beyond)
    step = span / (n if span == 360 else n - 1)
    assert len(split.train) == pytest.approx(split.arc / step + 1, abs=1.5)
    assert math.isclose(min(split.beyond), 10, abs_tol=step + 1e-6)
