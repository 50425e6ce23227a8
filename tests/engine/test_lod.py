"""The real-time path's level of detail chosen per mesh (:mod:`omnirecon.engine.lod`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from omnirecon.data import load_scene
from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.engine.lod import choose_level_of_detail, left_out_views
from omnirecon.mesh.ibr import level_of_detail, realtime_setting
from omnirecon.models.registry import build_model

pytestmark = pytest.mark.usefixtures("gl")  # skips without EGL, fails under CI=true (conftest)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A procedural scene, its exact mesh subdivided into 16x the faces (as fused meshes over-tessellate), a random
    omnirecon-tiny."""
    scene = load_scene(generate_scene(tmp_path_factory.mktemp("lod"), 5, SynthOptions(resolution=64, views=8)))
    mesh = trimesh.load(scene.mesh_path, process=False, force="mesh").subdivide().subdivide()
    torch.manual_seed(0)
    return scene, mesh, build_model("omnirecon-tiny").eval()


def test_left_out_views_spread_over_the_capture_and_leave_sources():
    assert left_out_views(list(range(12)), 3) == [2, 6, 10]
    assert left_out_views([4, 5], 1) == [5]
    assert left_out_views([4, 5, 6], 3) == [4, 5, 6]


def test_the_smallest_budget_within_the_tolerance_is_chosen_and_a_ruinous_one_never(setup):
    """With a 1-dB tolerance, a quarter of the over-tessellated mesh (measured 0.6 dB below it on the left-out photos,
    through a random model) is chosen and 4,000 faces (a 70th: 13 dB below) never; with no tolerance only the ceiling
    passes."""
    scene, mesh, model = setup
    train = list(range(len(scene)))
    setting = realtime_setting(scene)
    full = len(mesh.faces)
    keep = full // 4
    choice = choose_level_of_detail(model, mesh, scene, setting, train, budgets=(keep, 4000), sources=(),
                                    tolerance_db=1.0, ceiling=0, cull_tolerance_db=None,
                                    decimators=())  # the cull and the other collapses: their own tests
    assert [r["budget"] for r in choice.rows] == [0, keep, 4000]
    assert choice.rows[0]["faces"] == full and choice.rows[2]["faces"] <= 4000
    assert choice.rows[2]["psnr"] < choice.rows[0]["psnr"] - 1.0  # the ruinous budget shows in the score
    assert choice.face_budget == keep and choice.faces <= keep, choice.rows
    assert choice.rows[1]["psnr"] >= choice.rows[0]["psnr"] - 1.0
    assert len(choice.views) == 3 and choice.line().startswith(f"level of detail: {choice.faces:,} faces drawn")
    strict = choose_level_of_detail(model, mesh, scene, setting, train, budgets=(4000,), sources=(),
                                    tolerance_db=0.0, ceiling=0, decimators=())
    assert strict.face_budget == 0 and strict.faces == full


def test_nothing_is_measured_where_nothing_is_smaller(setup):
    scene, mesh, model = setup
    choice = choose_level_of_detail(model, mesh, scene, realtime_setting(scene), list(range(len(scene))),
                                    budgets=(10 * len(mesh.faces),), sources=(), ceiling=0, decimators=())
    assert choice.rows == [] and choice.face_budget == 0 and choice.faces == len(mesh.faces)
    assert choice.line() == f"level of detail: {len(mesh.faces):,} faces drawn (nothing smaller to measure)"
    assert choice.setting(realtime_setting(scene)) == realtime_setting(scene)  # nothing chosen: the setting as it was


def test_the_network_blend_takes_the_fewest_sources_within_the_tolerance(setup):
    """Fewer sources per frame are measured at the chosen budget against the ceiling row: with a tolerance no loss can
    reach every count passes and the fewest is chosen; with a negative one none; by default only a count that loses
    nothing on the left-out photos; the angle blend's sources are never changed."""
    scene, mesh, model = setup
    train = list(range(len(scene)))
    setting = realtime_setting(scene)
    assert setting["blend"] == "network" and setting["sources"] == 6
    loose = choose_level_of_detail(model, mesh, scene, setting, train, budgets=(), sources=(4, 3),
                                   sources_tolerance_db=100.0, strides=(), cull_tolerance_db=None, decimators=())
    assert [(r["faces"], r["sources"]) for r in loose.rows] == [(loose.faces, 6), (loose.faces, 4), (loose.faces, 3)]
    assert loose.sources == 3 and loose.setting(setting)["sources"] == 3 and " 3 sources per frame" in loose.line()
    strict = choose_level_of_detail(model, mesh, scene, setting, train, budgets=(), sources=(4, 3),
                                    sources_tolerance_db=-1.0, decimators=())
    assert strict.sources is None and strict.setting(setting) == setting
    angle = choose_level_of_detail(model, mesh, scene, {**setting, "blend": "angle", "sources": 0}, train, budgets=(),
                                   sources=(4, 3), sources_tolerance_db=100.0, decimators=(), angle_sources=())
    assert angle.rows == [] and angle.sources is None
    default = choose_level_of_detail(model, mesh, scene, setting, train, budgets=(), sources=(4, 3), strides=(),
                                     cull_tolerance_db=None, decimators=())
    by_rule = [r["sources"] for r in default.rows[1:] if r["psnr"] >= default.rows[0]["psnr"]]  # lose nothing
    assert default.sources == (by_rule[-1] if by_rule else None), default.rows


def test_the_angle_blend_takes_the_fewest_sources_per_point_within_the_tolerance(setup):
    """The angle blend's sources per point below the setting's are measured at the chosen budget against the ceiling
    row: with tolerances no loss can reach the fewest is blended (the setting then carries it, its sources per frame
    unchanged); with a negative one none; counts at or above the setting's are not measured; the network blend
    measures none; where none passes at the chosen budget, they are measured one budget up and drawn there."""
    scene, mesh, model = setup
    train = list(range(len(scene)))
    angle = {**realtime_setting(scene), "blend": "angle", "sources": 0, "angle_sources": 6}
    kw = dict(budgets=(), sources=(), strides=(), cull_tolerance_db=None, decimators=(), angle_sources=(8, 6, 4, 2))
    loose = choose_level_of_detail(model, mesh, scene, angle, train, tolerance_db=100.0, angle_tolerance_db=100.0, **kw)
    assert [r.get("angle_sources") for r in loose.rows] == [None, 4, 2], loose.rows
    assert loose.angle_sources == 2 and loose.setting(angle) == {**angle, "angle_sources": 2}
    assert " 2 sources per point" in loose.line() and loose.record()["angle_sources"] == 2
    strict = choose_level_of_detail(model, mesh, scene, angle, train, angle_tolerance_db=-1.0, **kw)
    assert len(strict.rows) == 3 and strict.angle_sources is None and strict.setting(angle) == angle
    network = choose_level_of_detail(model, mesh, scene, realtime_setting(scene), train, tolerance_db=100.0,
                                     angle_tolerance_db=100.0, **kw)
    assert network.rows == [] and network.angle_sources is None
    full = len(mesh.faces)  # as the network's sources per frame: where none passes at the chosen budget, one rung up
    kw = {**kw, "budgets": (full // 2, 4000), "angle_sources": (2,), "tolerance_db": 100.0, "ceiling": 0, "views": 1}
    none = choose_level_of_detail(model, mesh, scene, angle, train, angle_tolerance_db=-1.0, **kw)
    rows = {(r["budget"], r.get("angle_sources")): r["psnr"] for r in none.rows}
    assert set(rows) == {(0, None), (full // 2, None), (4000, None), (4000, 2), (full // 2, 2)}, none.rows
    assert none.face_budget == 4000 and none.angle_sources is None
    best = rows[(0, None)]
    assert rows[(4000, 2)] < rows[(full // 2, 2)], rows
    up = choose_level_of_detail(model, mesh, scene, angle, train, **kw,
                                angle_tolerance_db=(best - rows[(full // 2, 2)] + best - rows[(4000, 2)]) / 2)
    assert up.face_budget == full // 2 and up.angle_sources == 2, up.rows


def test_fewer_sources_that_lose_at_the_chosen_budget_are_measured_one_budget_up(setup):
    """Where no fewer-sources count passes at the chosen budget, the counts are measured one budget up (never two), and
    where one passes there, that budget is drawn with it."""
    scene, mesh, model = setup
    train = list(range(len(scene)))
    setting = realtime_setting(scene)
    full = len(mesh.faces)
    budgets = (full // 2, 4000)  # 4,000 faces: far below the others on the left-out photos
    none = choose_level_of_detail(model, mesh, scene, setting, train, budgets=budgets, sources=(3,), tolerance_db=100.0,
                                  ceiling=0, sources_tolerance_db=-1.0, strides=(), views=1, decimators=())
    assert none.face_budget == 4000 and none.sources is None, none.rows
    rows = {(r["budget"], r["sources"]): r["psnr"] for r in none.rows}
    assert set(rows) == {(0, 6), (full // 2, 6), (4000, 6), (4000, 3), (full // 2, 3)}  # one rung up, not two
    best = rows[(0, 6)]
    assert rows[(4000, 3)] < rows[(full // 2, 3)], rows
    tol = (best - rows[(full // 2, 3)] + best - rows[(4000, 3)]) / 2  # passes one rung up only
    up = choose_level_of_detail(model, mesh, scene, setting, train, budgets=budgets, sources=(3,), tolerance_db=100.0,
                                ceiling=0, sources_tolerance_db=tol, strides=(), views=1, decimators=())
    assert up.face_budget == full // 2 and up.sources == 3, up.rows
    assert up.faces == next(r["faces"] for r in up.rows if r["budget"] == full // 2)


def test_the_weight_stride_is_measured_at_the_chosen_sources_and_kept_within_its_tolerance(setup):
    """With 3 sources per frame (few enough for the GL pass's weight stride) a stride-2 row is measured at the chosen
    budget and sources: kept within a tolerance no loss can reach (the setting then carries it), never with a negative
    one; with 4 sources (too many for it) no stride is measured."""
    scene, mesh, model = setup
    train = list(range(len(scene)))
    setting = realtime_setting(scene)
    loose = choose_level_of_detail(model, mesh, scene, setting, train, budgets=(), sources=(3,),
                                   sources_tolerance_db=100.0, stride_tolerance_db=100.0, cull_tolerance_db=None, decimators=())
    assert [(r["sources"], r.get("weight_stride", 1)) for r in loose.rows] == [(6, 1), (3, 1), (3, 2)]
    assert loose.weight_stride == 2 and loose.setting(setting)["weight_stride"] == 2
    assert "the MLP every 2 px" in loose.line()
    strict = choose_level_of_detail(model, mesh, scene, setting, train, budgets=(), sources=(3,),
                                    sources_tolerance_db=100.0, stride_tolerance_db=-1.0, decimators=())
    assert strict.weight_stride == 1 and "weight_stride" not in strict.setting(setting)
    four = choose_level_of_detail(model, mesh, scene, setting, train, budgets=(), sources=(4,),
                                  sources_tolerance_db=100.0, stride_tolerance_db=100.0, cull_tolerance_db=None, decimators=())
    assert four.sources == 4 and four.weight_stride == 1 and len(four.rows) == 2


def test_only_the_faces_the_sources_see_are_drawn_where_they_lose_nothing(setup):
    """Every face drawn twice (the copy loses every depth test to the original, as completion's coplanar copies do):
    the chosen level is measured once more drawing only the faces the sources see, which leaves the copies out and
    renders the left-out photo as before but for the few faces only it sees, so it is drawn at the default tolerance;
    with a negative tolerance it is measured and not drawn; with none it is not measured."""
    scene, _, model = setup
    mesh = trimesh.Trimesh(*level_of_detail(trimesh.load(scene.mesh_path, process=False, force="mesh"), 3000),
                           process=False)  # faces large enough to judge at 64 px
    train = list(range(len(scene)))
    setting = realtime_setting(scene)
    twice = trimesh.Trimesh(mesh.vertices, np.concatenate([mesh.faces, mesh.faces]), process=False)
    F = len(twice.faces)
    kw = dict(budgets=(F - 8,), sources=(), tolerance_db=-1.0, ceiling=0, strides=(), views=1)  # the ceiling is drawn
    choice = choose_level_of_detail(model, twice, scene, setting, train, **kw, decimators=())
    assert [r.get("photographed", False) for r in choice.rows] == [False, False, True], choice.rows
    plain, seen = choice.rows[0], choice.rows[-1]
    assert seen["faces"] < 0.6 * F, choice.rows  # at most a few copies too small to judge are kept
    assert plain["psnr"] - 0.05 <= seen["psnr"] <= plain["psnr"], choice.rows
    assert choice.photographed and choice.face_budget == 0 and choice.faces == seen["faces"]
    assert "only the faces the photos see" in choice.line()
    drawn = choice.drawn(twice, scene.cameras[train])
    assert len(drawn[1]) < 0.6 * F  # every photo deciding: the copies left out again
    strict = choose_level_of_detail(model, twice, scene, setting, train, **kw, cull_tolerance_db=-1.0, decimators=())
    assert strict.rows[-1].get("photographed") and not strict.photographed and strict.faces == F
    assert len(strict.drawn(twice, scene.cameras[train])[1]) == F
    off = choose_level_of_detail(model, twice, scene, setting, train, **kw, cull_tolerance_db=None, decimators=())
    assert not any(r.get("photographed") for r in off.rows) and not off.photographed


def test_meshlabs_collapse_is_drawn_where_it_loses_nothing_against_the_chosen_level(setup):
    """MeshLab's collapse is measured at the chosen budget and below, with the chosen sources: a level is drawn only
    when it scores no worse than the chosen (fast-simplification) level and within the tolerance of the ceiling, the
    measuring stops at the first that fails, and the path draws that collapse (``LodChoice.drawn``); with a tolerance
    nothing can meet, it is measured at the chosen budget only and the fast level stays."""
    from omnirecon.mesh.clean import DECIMATORS

    scene, _, model = setup
    mesh = trimesh.load(scene.mesh_path, process=False, force="mesh").subdivide()  # smaller than the fixture's: quicker
    train = list(range(len(scene)))
    setting = realtime_setting(scene)
    keep = len(mesh.faces) // 4
    choice = choose_level_of_detail(model, mesh, scene, setting, train, budgets=(keep, keep // 4), sources=(),
                                    tolerance_db=1.0, ceiling=2 * keep, cull_tolerance_db=None, decimators=("meshlab",),
                                    views=1)  # the ceiling decimated too: the collapse is measured there at least
    fast = [r for r in choice.rows if "decimator" not in r]
    other = [r for r in choice.rows if r.get("decimator") == "meshlab"]
    chosen_fast = max((r for r in fast[1:] if r["psnr"] >= fast[0]["psnr"] - 1.0), key=lambda r: -r["budget"],
                      default=fast[0])
    assert other and other[0]["budget"] == chosen_fast["budget"]  # from the chosen budget down
    passed = [r["psnr"] >= max(chosen_fast["psnr"], fast[0]["psnr"] - 1.0) for r in other]
    assert all(passed[:-1])  # the measuring stops at the first level that fails
    if any(passed):
        last = other[len([p for p in passed if p]) - 1]
        assert choice.decimator == "meshlab" and choice.face_budget == last["budget"]
        drawn = choice.drawn(mesh, scene.cameras[train])  # the choice's own level, not decimated again
        again = level_of_detail(mesh, last["budget"], decimator="meshlab")
        assert len(drawn[1]) == last["faces"] == len(again[1]) and np.array_equal(drawn[0], again[0])
        assert "MeshLab's collapse" in choice.line()
    else:
        assert choice.decimator == "fast" and choice.face_budget == chosen_fast["budget"]
    never = choose_level_of_detail(model, mesh, scene, setting, train, budgets=(keep // 4,), sources=(),
                                   tolerance_db=-100.0, ceiling=keep, cull_tolerance_db=None, decimators=("meshlab",),
                                   views=1)
    assert never.decimator == "fast" and never.face_budget == keep
    assert [r["budget"] for r in never.rows if r.get("decimator")] == [keep]
    assert set(DECIMATORS) == {"fast", "meshlab"}
