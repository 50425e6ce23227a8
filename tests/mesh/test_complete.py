"""Complete surfaces: every pixel of every training view of a forward-facing scene is on the mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.engine.scenes import load_at_resolution
from omnirecon.mesh.build import MeshOptions, mesh_from_model
from omnirecon.mesh.complete import DepthRenderer, pixel_grid_surface
from tests.mesh.test_mesh import ring_cameras


@pytest.fixture(scope="module")
def forward_scene(tmp_path_factory) -> Path:
    """A 48 x 48 forward-facing procedural scene of 12 views."""
    return generate_scene(tmp_path_factory.mktemp("fwd"), 900_321, SynthOptions(rig="forward", resolution=48, views=12))


@pytest.mark.parametrize("depth", ["oracle", "stereo"])
def test_a_forward_scene_is_meshed_with_full_coverage_of_its_training_views(forward_scene, depth):
    scene = load_at_resolution(forward_scene, 48)
    assert scene.rig == "forward"
    views = scene.splits["train"]
    made = mesh_from_model(None, scene, views, MeshOptions(depth=depth, max_faces=20_000))
    comp = made.info["completion"]
    r = DepthRenderer(made.mesh)
    covered = [float((r(scene.cameras[v]) > 0).mean()) for v in views]
    r.close()
    assert min(covered) == 1.0, covered  # every pixel of every training view
    assert comp["coverage_before"] < 1.0 and comp["fill_faces"] > 0  # the completion did the work
    if depth == "oracle":  # the fill sits on the exact surface where the exact depth exists
        d = made.mesh.vertices
        lo, hi = scene.bounds.numpy()
        assert np.isfinite(d).all() and (d > lo - 0.5).all() and (d < hi + 0.5).all()


def test_pixel_grid_surface_covers_every_pixel_centre_whatever_the_depth():
    cam = ring_cameras(2, res=24)[0]
    g = torch.Generator().manual_seed(0)
    depth = (2.0 + torch.rand(24, 24, generator=g)).numpy()  # rough depth: edges everywhere
    region = np.zeros((24, 24), dtype=bool)
    region[3:20, 5:22] = True
    fill = pixel_grid_surface(cam, depth, region)
    assert len(fill.faces) == 2 * region.sum()
    r = DepthRenderer(fill)
    hit = r(cam) > 0
    r.close()
    assert (hit == region).all()


def test_completion_keeps_an_empty_background_empty():
    """Object scene, no masks: only pixels where the depth source saw a surface are completed."""
    cams = ring_cameras(2, res=32)
    from omnirecon.mesh.complete import complete_surface
    from tests.mesh.test_mesh import sphere_depth

    depth = sphere_depth(cams, 0.8)
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    mesh, info = complete_surface(empty, cams, depth, torch.tensor([[-1.0] * 3, [1.0] * 3]))
    r = DepthRenderer(mesh)
    for i in range(2):
        hit = r(cams[i]) > 0
        assert (hit == (depth[i] > 0).numpy()).mean() > 0.99
    r.close()
