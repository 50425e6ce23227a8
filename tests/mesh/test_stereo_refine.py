"""Photometric refinement of depth maps: a biased depth comes back to the exact one; the exact one stays."""

from __future__ import annotations

import pytest

from omnirecon.errors import InputError
from omnirecon.mesh.stereo_refine import RefineOptions, refine_depths
from tests.mesh.test_stereo import textured_plane_views


def _abs_rel(depth, exact):
    ok = (depth > 0) & (exact > 0)
    return float(((depth[ok] - exact[ok]).abs() / exact[ok]).mean())


def test_a_depth_biased_3_percent_far_is_refined_back_and_the_exact_depth_stays():
    images, cams, exact = textured_plane_views([[0.0, 0, 0], [0.3, 0, 0], [0.0, 0.3, 0], [-0.3, 0, 0]])
    views = [0, 1, 2, 3]
    biased = exact * 1.03
    biased[:, :, :20] = 0  # pixels without depth stay without
    out = refine_depths(images, cams, views, biased)
    inner = (slice(None), slice(10, -10), slice(30, -10))  # away from the image borders and the hole
    assert _abs_rel(biased[inner], exact[inner]) > 0.029
    assert _abs_rel(out[inner], exact[inner]) < 0.005
    assert (out[:, :, :20] == 0).all()
    kept = refine_depths(images, cams, views, exact.clone())
    assert _abs_rel(kept[inner], exact[inner]) < 0.003


@pytest.mark.parametrize("field,value", [("span", 0.0), ("steps", 4), ("best", 5), ("window", 2), ("truncate", 0.0),
                                         ("propagate", -1), ("propagate_passes", 0), ("propagate_gain", -0.1)])
def test_bad_refine_options_are_one_line_errors(field, value):
    with pytest.raises(InputError) as e:
        RefineOptions(**{field: value}).check()
    assert "\n" not in str(e.value) and "refine option" in str(e.value) and "use" in str(e.value)


def test_bad_refine_mode_is_a_one_line_error():
    from omnirecon.mesh.build import MeshOptions

    with pytest.raises(InputError) as e:
        MeshOptions(refine="everything").check()
    assert "\n" not in str(e.value) and "refine" in str(e.value)


def test_propagation_reaches_a_gross_error_the_sweep_cannot_and_keeps_the_exact_depth():
    # a 2-px band 15 % too near (stereo giving the ground beside an object's base the object's depth): beyond the
    # sweep's span; propagation offers each pixel its neighbours' depths 1-2 px away, and the photos pick the right one
    images, cams, exact = textured_plane_views([[0.0, 0, 0], [0.3, 0, 0], [0.0, 0.3, 0], [-0.3, 0, 0]])
    views = [0, 1, 2, 3]
    wrong = exact.clone()
    wrong[:, :, 40:42] *= 0.85
    band = (slice(None), slice(10, -10), slice(40, 42))
    swept = refine_depths(images, cams, views, wrong, RefineOptions(propagate=0))
    assert _abs_rel(swept[band], exact[band]) > 0.1
    out = refine_depths(images, cams, views, wrong, RefineOptions(propagate=2))
    assert _abs_rel(out[band], exact[band]) < 0.01
    kept = refine_depths(images, cams, views, exact.clone(), RefineOptions(propagate=2))
    inner = (slice(None), slice(10, -10), slice(10, -10))
    assert _abs_rel(kept[inner], exact[inner]) < 0.003


def test_window_cost_at_the_pixels_with_depth_equals_the_dense_cost():
    """The scorer costs only the pixels with depth, each window from their rows: the dense reference (every pixel's
    cost, windows by ``F.unfold`` with the pixels without depth weighted 0) gives the same numbers there."""
    import torch
    import torch.nn.functional as F

    from omnirecon.mesh.stereo_refine import _Scorer, support_weights

    images, cams, exact = textured_plane_views([[0.0, 0, 0], [0.3, 0, 0], [0.0, 0.3, 0]])
    depth = exact[0].clone()
    depth[torch.rand(depth.shape, generator=torch.Generator().manual_seed(0)) < 0.3] = 0  # scattered holes
    depth[:, :12] = 0
    o = RefineOptions()
    score = _Scorer(images, cams, 0, depth > 0, [1, 2], o)
    d = (depth * 1.01).reshape(-1)
    got = score(d)
    # dense reference
    H, W = depth.shape
    valid = (depth > 0).float()
    w = o.window
    weights = support_weights(images[0].float(), o) * F.unfold(valid[None, None], w, padding=w // 2)[0]
    cam = cams[0].to(dtype=torch.float32)
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    rays = torch.stack([(u - cam.cx[0]) / cam.fx[0], (v - cam.cy[0]) / cam.fy[0], torch.ones_like(u)], -1)
    pts = cam.centers[0] + (rays.reshape(-1, 3) @ cam.R[0].T) * d[:, None]  # [HW, 3]
    oc = cams[[1, 2]].to(dtype=torch.float32)
    p = oc.project(pts)
    grid = (p.uv / torch.tensor([W, H]) * 2 - 1)[:, None]  # [J, 1, HW, 2]
    src = images[[1, 2]].float().permute(0, 3, 1, 2)
    c = (F.grid_sample(src, grid, align_corners=False, padding_mode="border")[:, :, 0]
         - images[0].reshape(-1, 3).T[None]).abs().sum(1).clamp_max(o.truncate)
    c = torch.where(p.in_image & (p.depth > 1e-6), c, torch.full_like(c, o.truncate))
    agg = (F.unfold(c.reshape(2, 1, H, W), w, padding=w // 2) * weights[None]).sum(1) / weights.sum(0).clamp_min(1e-8)
    ref = agg.sort(0).values[: o.best].mean(0)
    at = (depth > 0).reshape(-1)
    assert at.float().mean() > 0.4
    assert torch.allclose(got[at], ref[at], atol=1e-5), float((got[at] - ref[at]).abs().max())


def _cost_before(score, d):
    """The scorer's cost as computed before the window sums went through index_select and the sort through running
    minima (commit 0dd8dc3): the reference, bit for bit."""
    import torch
    import torch.nn.functional as F

    o = score.options
    pts = score.centre + score.rays * d[score.at][:, None]
    uvz = score.proj[:, :, :3] @ pts.T + score.proj[:, :, 3:]
    z = uvz[:, 2]
    uv = uvz[:, :2] / z.clamp_min(1e-6)[:, None]
    grid = (uv / score.size[None, :, None] * 2 - 1).permute(0, 2, 1)[:, None]
    sampled = F.grid_sample(score.src, grid, mode="bilinear", padding_mode="border", align_corners=False)[:, :, 0]
    c = (sampled - score.ref_at).abs().sum(1).clamp_max(o.truncate)
    seen = (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < score.oc.width) & (uv[:, 1] >= 0) & (uv[:, 1] < score.oc.height)
    c = torch.where(seen, c, torch.full_like(c, o.truncate))
    c = torch.cat([c, torch.zeros_like(c[:, :1])], 1)
    agg = (c[:, score.window] * score.weights[None]).sum(1) / score.norm
    out = torch.full((score.H * score.W,), float(o.truncate))
    out[score.at] = agg.sort(0).values[: o.best].mean(0)
    return out


@pytest.mark.parametrize("best, others", [(2, [1, 2, 3]), (2, [1, 2]), (1, [1, 2, 3]), (3, [1, 2, 3])])
def test_window_cost_equals_the_previous_computation_bit_for_bit(best, others):
    """index_select + in-place weighting + running minima (:func:`lowest_mean`) give the costs the gather-and-sort
    code gave, bit for bit, for every number of lowest costs kept (ties included: quantised depths)."""
    import torch

    from omnirecon.mesh.stereo_refine import _Scorer, lowest_mean

    images, cams, exact = textured_plane_views([[0.0, 0, 0], [0.3, 0, 0], [0.0, 0.3, 0], [-0.3, 0.1, 0]])
    depth = exact[0].clone()
    depth[torch.rand(depth.shape, generator=torch.Generator().manual_seed(1)) < 0.3] = 0
    score = _Scorer(images, cams, 0, depth > 0, others, RefineOptions(best=best))
    for scale in (0.97, 1.0, 1.013):
        d = (depth * scale).reshape(-1)
        assert torch.equal(score(d), _cost_before(score, d))
    ties = torch.randint(0, 4, (4, 1000), generator=torch.Generator().manual_seed(2)).float()
    for k in (1, 2, 3):
        assert torch.equal(lowest_mean(ties, k), ties.sort(0).values[:k].mean(0))
