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
    faces = made.info["faces"]  # the face budget holds for the written mesh, fills and backdrop included
    assert len(made.mesh.faces) == faces["final"] <= 20_000
    v = np.asarray(made.mesh.vertices)  # welded: no two vertices at the same place, every one used
    assert len(np.unique(v, axis=0)) == len(v) and len(np.unique(made.mesh.faces)) == len(v)
    if depth == "stereo":  # fused 20k + fills and backdrop went over: the fused surface got what the fills left
        assert faces["over_budget"] > 20_000 and faces["decimated"] < 20_000 - comp["fill_faces"]
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


def test_a_fill_in_front_of_what_another_view_sees_is_flagged():
    """``occluding``: a point nearer than the surface another view sees along its ray is flagged; points on
    that surface, behind it, or where the other view sees nothing are not."""
    from omnirecon.mesh.complete import occluding
    from tests.mesh.test_mesh import sphere_depth

    cams = ring_cameras(8, res=32)[[0, 1]]  # 45 degrees apart
    seen = sphere_depth(cams, 0.8).numpy()  # what each view sees of the sphere
    region = np.ones((32, 32), dtype=bool)
    on = occluding(cams[0], seen[0], region, cams[1:], seen[1:], 0.02)
    assert not on.any()  # the sphere's own points hide nothing view 1 sees
    near = np.where(seen[0] > 0, 0.9 * seen[0], 0.0)  # floating just in front of the sphere
    flagged = occluding(cams[0], near, region, cams[1:], seen[1:], 0.02)
    assert flagged.any() and not flagged[seen[0] <= 0].any()
    far = np.where(seen[0] > 0, 1.5 * seen[0], 0.0)  # behind the sphere: hidden, not hiding
    assert not occluding(cams[0], far, region, cams[1:], seen[1:], 0.02).any()


def two_views_of_a_wall(res: int = 32, f: float = 30.0):
    """Two cameras 1 apart on x at z = -3 looking along +z, and a wall at z = 0 (a grid of 40 x 40 quads
    over [-2, 2]^2) without the quads around its centre: a hole both views see."""
    from omnirecon.cameras import Cameras

    c2w = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    c2w[:, 0, 3] = torch.tensor([-0.5, 0.5])
    c2w[:, 2, 3] = -3.0
    cams = Cameras(torch.full((2,), f), torch.full((2,), f), res / 2, res / 2, c2w, res, res)
    wall = trimesh.creation.box((4.0, 4.0, 1e-3)).subdivide().subdivide().subdivide().subdivide()
    centre = np.abs(wall.triangles_center[:, :2]).max(1)
    wall = wall.submesh([np.nonzero((centre > 0.3) & (wall.triangles_center[:, 2] < 0))[0]], append=True)
    return cams, wall


@pytest.mark.parametrize("check", [True, False])
def test_completion_puts_no_fill_in_front_of_a_surface_another_view_sees(check):
    """View 0's map has a wrong, too-near depth in the wall's hole: a fill there would hide wall that view 1
    sees. With the check it is left out (an object rig: not forward-facing); without, view 1 sees it."""
    from omnirecon.mesh.complete import complete_surface

    cams, wall = two_views_of_a_wall()
    before = DepthRenderer(wall)
    seen = np.stack([before(cams[i]) for i in range(2)])
    before.close()
    hole = seen[0] <= 0
    assert 0 < hole.sum() < 0.3 * hole.size
    maps = torch.zeros(2, 32, 32)
    maps[0] = torch.from_numpy(np.where(hole, 1.5, 3.0)).float()  # the hole at half the wall's depth
    mesh, info = complete_surface(wall, cams, maps, torch.tensor([[-2.0, -2.0, -1.0], [2.0, 2.0, 1.0]]),
                                  occlusion_rel=0.02 if check else None)
    r = DepthRenderer(mesh)
    after = r(cams[1])
    r.close()
    hidden = (seen[1] > 0) & (after > 0) & (after < 0.98 * seen[1])  # view 1 now sees a fill in front of the wall
    if check:
        assert info["occluding"] > 0 and hidden.sum() == 0
    else:
        assert info["fill_faces"] > 0 and hidden.sum() > 0


def test_the_backdrop_layer_covers_views_between_and_past_the_training_views(forward_scene):
    """Forward-facing scene: held-out views and the training views grown by 5 % see surface at every pixel; the
    backdrop lies on the bounds' far side."""
    from omnirecon.mesh.complete import backdrop_sheet, padded_camera
    from omnirecon.mesh.fusion import exit_depth

    scene = load_at_resolution(forward_scene, 48)
    made = mesh_from_model(None, scene, scene.splits["train"], MeshOptions(depth="stereo", max_faces=20_000))
    assert made.info["completion"]["backdrop_faces"] > 0
    r = DepthRenderer(made.mesh)
    for v in scene.splits["test"]:
        assert (r(scene.cameras[v]) > 0).all()
    assert (r(padded_camera(scene.cameras[scene.splits["train"][0]], 2)) > 0).all()
    r.close()
    cams = scene.cameras[scene.splits["train"]]
    sheet = backdrop_sheet(cams, scene.bounds, 0.0, cell=1)
    r = DepthRenderer(sheet)
    d, far = r(cams[0]), exit_depth(cams[0], scene.bounds)[0].numpy()
    r.close()
    ok = (d > 0) & (far > 0)
    rel = np.abs(d[ok] - far[ok]) / far[ok]  # other views' sheets may lie in front where the box's faces meet
    assert ok.mean() > 0.95 and np.quantile(rel, 0.9) < 0.05 and np.median(rel) < 0.005  # corners sit on neighbouring rays


def test_the_hull_trim_never_deletes_surface_a_view_sees_and_nothing_else_covers():
    """``clean.restore_seen``: after a trim that dropped a wall (z = 4), a square in front of it (z = 2) and a quad
    beside them, the faces camera 0 sees first at its mask's pixels that the kept faces leave uncovered come back
    (the square, the wall around it), never faces outside the mask (the side quad) nor faces hidden behind kept ones."""
    from omnirecon.cameras import Cameras, look_at
    from omnirecon.mesh.clean import restore_seen
    from tests.mesh.test_mesh_render import quad

    parts = [quad([0, 0, 4], 2.0), quad([0, 0, 2], 0.3), quad([0, 0, 6], 0.5), quad([1.5, 0, 3], 0.1)]
    mesh = trimesh.Trimesh(np.concatenate([v for v, _ in parts]),
                           np.concatenate([f + 4 * i for i, (_, f) in enumerate(parts)]), process=False)
    W = H = 32
    eye = torch.tensor([[0.0, 0, 0]])
    c2w = look_at(eye, eye + torch.tensor([0, 0, 1.0]), torch.tensor([0, -1.0, 0]))
    f = torch.full((1,), 20.0, dtype=torch.float64)
    cams = Cameras(f, f, f * 0 + W / 2, f * 0 + H / 2, c2w.double(), W, H)
    masks = np.zeros((1, H, W), dtype=bool)
    masks[0, 8:24, 8:24] = True  # the wall covers all of it, the square pixels 11-20, the side quad lies at u ~ 26
    keep = np.array([False] * 4 + [True] * 2 + [False] * 2)  # the trim kept only the small far quad, behind the square
    restored = restore_seen(mesh, keep, cams, masks)
    assert restored[:4].all()  # the wall and the square: seen first in the mask, nothing kept covers those pixels
    assert restored[4:6].all()  # the far quad stays
    assert not restored[6:].any()  # the side quad: outside the mask
    keep = np.array([False, False, True, True, True, True, False, False])  # wall dropped, square kept
    masks[0] = False
    masks[0, 13:19, 13:19] = True  # inside the square's silhouette only
    assert restore_seen(mesh, keep, cams, masks).tolist() == keep.tolist()  # the mask is covered: nothing comes back


def test_completion_covers_the_content_pixels_the_depth_maps_leave_out():
    """Object scene, no masks: a view's map lost the sphere's outline (a 3-px ring, as stereo near a known background
    colour). Completion from the maps alone leaves the ring uncovered; given the content pixels (the photo's
    non-background colour) it covers them too, and still nothing beyond them."""
    from scipy.ndimage import binary_erosion

    from omnirecon.mesh.complete import complete_surface
    from tests.mesh.test_mesh import sphere_depth

    cams = ring_cameras(8, res=32)[[0]]  # one view: no other view's fill to cover its outline
    full = sphere_depth(cams, 0.4)  # [1, 32, 32]
    content = (full > 0).numpy()
    inner = np.stack([binary_erosion(c, np.ones((7, 7), bool)) for c in content])
    maps = torch.where(torch.from_numpy(inner), full, torch.zeros_like(full))
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    bounds = torch.tensor([[-1.0] * 3, [1.0] * 3])
    for given in (None, content):
        mesh, info = complete_surface(empty, cams, maps, bounds, content=given)
        r = DepthRenderer(mesh)
        hit = (r(cams[0]) > 0)[None]
        r.close()
        ring = content & ~inner
        assert ring.sum() > 50
        if given is None:
            assert hit[ring].mean() < 0.5
        else:
            assert hit[ring].mean() > 0.99 and not hit[~content].any()


def test_content_pixels_are_the_photos_non_background_colour(tmp_path):
    """``content_pixels`` on a procedural object scene (known background colour): the pixels the exact mesh covers,
    but for antialiased outline pixels; none more than a pixel away from it. No background colour: None."""
    from scipy.ndimage import binary_dilation

    from omnirecon.mesh.geometry import ground_truth_mesh, mesh_depth
    from omnirecon.mesh.stages import content_pixels

    scene = load_at_resolution(generate_scene(tmp_path, 900_322, SynthOptions(resolution=48, views=4)), 48)
    assert scene.background is not None
    got = content_pixels(scene, [0, 1], 0.15, None)
    gt = ground_truth_mesh(scene)
    covered = np.stack([mesh_depth(gt, scene.cameras[v]) > 0 for v in (0, 1)])
    near = np.stack([binary_dilation(c, np.ones((3, 3), bool)) for c in covered])
    assert got.shape == covered.shape and not got[~near].any()
    assert got[covered].mean() > 0.95
    scene.background = None
    assert content_pixels(scene, [0, 1], 0.15, None) is None


@pytest.mark.parametrize("value", [-0.1, 1.0, float("nan")])
def test_a_bad_content_fill_is_a_one_line_error(value):
    from omnirecon.errors import InputError

    with pytest.raises(InputError, match=r"content_fill must be in \[0, 1\)"):
        MeshOptions(content_fill=value).check()


@pytest.mark.parametrize("budget", [576, 144])
def test_a_level_of_detail_keeps_the_pixel_fills_whole(budget):
    """Completion's pixel fills give each pixel its own four corners (equal to its neighbours' where the depths agree):
    :func:`~omnirecon.mesh.clean.weld` joins them into one grid, and the real-time path's level of detail
    (:func:`~omnirecon.mesh.ibr.level_of_detail`, welded, then decimated) keeps covering the view at the surface's
    depth within the face budget. Decimated unwelded, each quad was a border of its own and the collapse deleted most of
    them (13 % of the pixels left covered at 576 faces)."""
    from omnirecon.mesh.clean import weld
    from omnirecon.mesh.ibr import level_of_detail

    cam = ring_cameras(2, res=48)[0]
    u = np.arange(48)[None].repeat(48, 0)
    depth = 2.5 + 0.02 * np.sin(u / 3.0)  # a smooth surface: every corner shared with the pixels around it
    fill = pixel_grid_surface(cam, depth, np.ones((48, 48), dtype=bool))
    assert len(fill.vertices) == 49 * 49 and len(fill.faces) == 2 * 48 * 48  # welded as made
    v, f = weld(fill.vertices, fill.faces)
    assert len(v) == len(fill.vertices) and (f == fill.faces).all()
    corners = trimesh.Trimesh(fill.vertices[fill.faces].reshape(-1, 3), np.arange(6 * 48 * 48).reshape(-1, 3),
                              process=False)  # the same triangles, each with corners of its own
    v, f = weld(corners.vertices, corners.faces)
    assert len(v) == 49 * 49 and len(f) == len(fill.faces)
    lv, lf = level_of_detail(corners, budget)
    assert len(lf) <= budget
    r = DepthRenderer(trimesh.Trimesh(lv, lf, process=False))
    z = r(cam)
    r.close()
    assert (z > 0).mean() > 0.97
    assert np.abs(z - depth)[z > 0].max() < 0.005 * 2.5


def test_decimation_meets_the_budget_where_fast_simplification_stops_short():
    """On a welded pixel grid of a slanted surface fast-simplification refuses every collapse below about 1,240 faces;
    :func:`~omnirecon.mesh.clean.decimate` still returns at most the budget."""
    from omnirecon.mesh.clean import decimate

    cam = ring_cameras(2, res=48)[0]
    depth = 2.0 + 0.01 * np.arange(48)[None].repeat(48, 0)
    fill = pixel_grid_surface(cam, depth, np.ones((48, 48), dtype=bool))
    small = decimate(fill, 576)  # welded as made
    assert len(small.faces) <= 576
    r = DepthRenderer(small)
    assert (r(cam) > 0).mean() > 0.97
    r.close()
