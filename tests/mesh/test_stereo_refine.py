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
