"""Classical stereo: depth on a procedural pair against its exact depth; bad options are one-line errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from omnirecon.cameras import Cameras, look_at
from omnirecon.errors import InputError
from omnirecon.mesh.stereo import StereoOptions, stereo_depths, stereo_neighbours

W, H, F = 160, 120, 150.0


def textured_plane_views(centres: list[list[float]], target: list[float] | None = None):
    """Cameras at ``centres`` looking down +z (or at ``target``) at a slanted plane ``z = 4 + 0.3 x`` with a
    random texture: the images and the exact z-depth of every pixel."""
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(1, 3, 64, 64, generator=g)
    c2w = torch.cat([look_at(torch.tensor(c, dtype=torch.float64),
                             torch.tensor(c, dtype=torch.float64) + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
                             if target is None else torch.tensor(target, dtype=torch.float64),
                             torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)) for c in centres])
    n = len(centres)
    cams = Cameras(torch.full((n,), F, dtype=torch.float64), torch.full((n,), F, dtype=torch.float64),
                   torch.full((n,), W / 2, dtype=torch.float64), torch.full((n,), H / 2, dtype=torch.float64), c2w, W, H)
    o, d = cams.image_rays(normalize=False)  # [N, H, W, 3], camera z of d is 1
    # plane z = 4 + 0.3 x  ->  o_z + t d_z = 4 + 0.3 (o_x + t d_x)
    t = (4 + 0.3 * o[..., 0] - o[..., 2]) / (d[..., 2] - 0.3 * d[..., 0])
    p = o + t[..., None] * d
    grid = torch.stack([p[..., 0] / 3.0, p[..., 1] / 2.5], -1).float()  # plane coordinates -> [-1, 1]
    images = torch.nn.functional.grid_sample(tex.expand(n, -1, -1, -1), grid, mode="bilinear", align_corners=False,
                                             padding_mode="reflection").permute(0, 2, 3, 1)
    return images.contiguous(), cams, t.float()


def test_stereo_depth_on_a_procedural_pair_is_within_2_percent():
    # a rectified pair (baseline along x) and a third view above: depth at view 0 from two pairs
    images, cams, exact = textured_plane_views([[0.0, 0, 0], [0.3, 0, 0], [0.0, 0.3, 0]])
    bounds = torch.tensor([[-4.0, -3.0, 2.0], [4.0, 3.0, 7.0]])
    out = stereo_depths(images, cams, [0, 1, 2], bounds)
    depth = out["depth"][0]
    ok = depth > 0
    assert ok.float().mean() > 0.8  # most of the view is matched (the left band too: padding)
    abs_rel = float(((depth[ok] - exact[0][ok]).abs() / exact[0][ok]).mean())
    assert abs_rel < 0.02, abs_rel
    assert out["confidence"][0][ok].min() > 0 and out["confidence"].max() <= 1
    # the right view of the pair (matched mirrored) is as good
    ok1 = out["depth"][1] > 0
    assert ok1.float().mean() > 0.8
    assert float(((out["depth"][1][ok1] - exact[1][ok1]).abs() / exact[1][ok1]).mean()) < 0.02


def test_converging_cameras_keep_their_correspondences_on_the_canvas():
    """Two cameras 33 degrees apart looking at one point: on the rectified canvas, what the left image shows at
    its left lies further left than the other canvas reaches unless that canvas is shifted by the smallest
    disparity (without the shift the demo scene's 32-degree pairs read depths 90 % too far)."""
    images, cams, exact = textured_plane_views([[-1.2, 0, 0], [1.2, 0, 0]], target=[0.0, 0.0, 4.0])
    out = stereo_depths(images, cams, [0, 1], torch.tensor([[-4.0, -3.0, 2.0], [4.0, 3.0, 7.0]]))
    o, d = cams.image_rays(normalize=False)  # [2, H, W, 3]
    for v in (0, 1):  # the left view and the right one (matched mirrored)
        depth = out["depth"][v]
        ok = depth > 0
        points = (o[v] + exact[v][..., None].double() * d[v]).reshape(-1, 3)
        seen = cams[1 - v].project(points).in_image[0].reshape(H, W)  # what the other view sees (79 %, 89 %)
        assert ok.float().mean() > 0.5 * seen.float().mean(), float(ok.float().mean())  # unshifted: 21 %, 17 %
        assert float(((depth[ok] - exact[v][ok]).abs() / exact[v][ok]).median()) < 0.01
        assert float((((depth[ok] - exact[v][ok]).abs() / exact[v][ok]) < 0.03).float().mean()) > 0.9


def test_the_disparity_range_covers_what_the_view_sees_of_the_bounds():
    """The search range comes from the part of the bounds inside the view: it holds the plane's disparities, a box
    reaching far beyond the field of view does not widen it, and a box corner beside and behind a camera that looks
    30 degrees sideways (in no ray of the view) does not stretch it to ``max_disparities`` as the box's corners did."""
    from omnirecon.mesh.stereo import disparity_range, rectify_pair

    opts = StereoOptions(max_disparities=1024)
    a = math.radians(30)
    for centres, target, bounds in (
            ([[0.0, 0, 0], [0.3, 0, 0]], None, [[-4.0, -3.0, 2.0], [4.0, 3.0, 7.0]]),
            ([[0.0, 0, 0], [0.3, 0, 0]], None, [[-40.0, -30.0, 2.0], [40.0, 30.0, 7.0]]),
            ([[0.0, 0, 0], [0.3 * math.cos(a), 0, -0.3 * math.sin(a)]], [1e3 * math.sin(a), 0, 1e3 * math.cos(a)],
             [[-4.0, -8.0, 2.0], [15.0, 8.0, 12.0]])):
        _, cams, exact = textured_plane_views(centres, target)
        rect = rectify_pair(cams[0], cams[1])
        o, d = cams.image_rays(normalize=False)
        points = (o[0] + exact[0][..., None].double() * d[0]).reshape(-1, 3).numpy()
        true = rect.f * rect.baseline / ((points - cams[0].centers[0].numpy()) @ rect.R[:, 2])  # [H*W] the plane's
        dmin, num = disparity_range(rect, cams[0].centers[0].numpy(), torch.tensor(bounds), opts, cams[0])
        assert dmin <= true.min() and true.max() <= dmin + num and num <= 32, (dmin, num)  # corners: 1024 on the last


def test_neighbours_skip_baselines_along_the_optical_axis():
    _, cams, _ = textured_plane_views([[0.0, 0, 0], [0.0, 0, 0.5], [0.4, 0, 0], [0.2, 0, 0]])
    near = stereo_neighbours(cams, [0, 1, 2, 3], StereoOptions(pairs=3))
    assert 1 not in near[0] and near[0][0] == 3  # the forward step is no stereo pair; the short sideways one first


@pytest.mark.parametrize("field,value", [("pairs", 0), ("block_size", 4), ("p2", 100), ("agree", 0.0),
                                         ("min_axis_angle", math.nan), ("max_disparities", 8),
                                         ("match_side", -1)])
def test_bad_stereo_options_are_one_line_errors(field, value):
    opts = StereoOptions(**{field: value})
    with pytest.raises(InputError) as e:
        opts.check()
    assert "\n" not in str(e.value) and "stereo option" in str(e.value) and "use" in str(e.value)


def test_stereo_time_per_view_is_recorded_for_the_bench():
    images, cams, _ = textured_plane_views([[0.0, 0, 0], [0.3, 0, 0]])
    out = stereo_depths(images, cams, [0, 1], torch.tensor([[-4.0, -3.0, 2.0], [4.0, 3.0, 7.0]]))
    assert out["pairs"] == [[1], [0]] and np.isfinite(out["depth"].numpy()).all()


def test_a_depth_no_other_view_confirms_is_dropped():
    """Multi-view geometric consistency (StereoOptions.confirm): a patch of one view's map pushed 20 %
    off is confirmed by no other view; the exact depth around it is confirmed by all."""
    from omnirecon.mesh.stereo import unconfirmed

    _, cams, exact = textured_plane_views([[0.0, 0, 0], [0.3, 0, 0], [0.0, 0.3, 0], [0.3, 0.3, 0]])
    depths = exact.clone()
    depths[0, 40:60, 60:90] *= 1.2
    lone = unconfirmed(cams, depths, rel=0.02, need=1)
    assert bool(lone[0, 42:58, 62:88].all())
    seen = torch.zeros_like(lone[0])
    seen[20:100, 30:130] = True  # well inside the other views' images
    assert not bool(lone[1:, 20:100, 30:130].any()) and not bool(lone[0][seen & (depths[0] == exact[0])].any())
    assert not bool(unconfirmed(cams, exact, rel=0.02, need=3)[:, 20:100, 30:130].any())


def test_matching_on_a_finer_grid_reads_depth_back_at_the_photos_pixels():
    # the same pair matched on its own 160 px grid and on a 320 px one: depth at the photo's pixels either
    # way, and the finer grid's sub-pixel disparity is at least as accurate
    images, cams, exact = textured_plane_views([[0.0, 0, 0], [0.3, 0, 0]])
    bounds = torch.tensor([[-4.0, -3.0, 2.0], [4.0, 3.0, 7.0]])
    err = {}
    for side in (0, 320):
        depth = stereo_depths(images, cams, [0, 1], bounds, StereoOptions(match_side=side))["depth"][0]
        ok = depth > 0
        assert depth.shape == (H, W) and ok.float().mean() > 0.8
        err[side] = float(((depth[ok] - exact[0][ok]).abs() / exact[0][ok]).mean())
    assert err[320] < 0.02 and err[320] <= err[0] * 1.1, err


def test_the_default_matches_small_photos_on_twice_their_grid():
    """``StereoOptions.match_side``'s default matches photos up to 320 px (fern's 336x252 at 1.9x, DTU's 400x300 at 1.6x)
    on a grid twice their size: on a 160 px pair its depth is at least as accurate as the photos' own grid's."""
    images, cams, exact = textured_plane_views([[0.0, 0, 0], [0.3, 0, 0]])
    bounds = torch.tensor([[-4.0, -3.0, 2.0], [4.0, 3.0, 7.0]])
    assert StereoOptions().match_side >= 2 * 320
    err = {}
    for opts in (StereoOptions(), StereoOptions(match_side=0)):
        depth = stereo_depths(images, cams, [0, 1], bounds, opts)["depth"][0]
        ok = depth > 0
        err[opts.match_side] = float(((depth[ok] - exact[0][ok]).abs() / exact[0][ok]).mean())
    assert err[StereoOptions().match_side] <= err[0], err
