"""The Depth sources section: the table, the per-goal gap split and the photos -> mesh timing rows."""

from __future__ import annotations

import json

from bench.report.depth_sources import section


def test_section_splits_each_gap_and_lists_timing(tmp_path):
    from omnirecon.provenance import provenance

    prov = provenance(seed=0)
    rows = [
        {"scene": "fern", "source": "stereo+model", "psnr": {"before": 20.0, "after": 21.0},
         "psnr_covered": {"before": 21.0, "after": 22.0}, "coverage": 0.98},
        {"scene": "demo", "source": "exact mesh", "psnr": {"before": 22.0, "after": None}, "coverage": 0.6},
        {"scene": "demo", "source": "oracle", "psnr": {"before": 21.5, "after": None}, "coverage": 0.6},
        {"scene": "demo", "source": "stereo+fill", "psnr": {"before": 19.0, "after": 19.5}, "coverage": 0.6},
        {"scene": "fern", "source": "stereo", "timing": True, "photos": 20, "resolution": [336, 252],
         "cpu_seconds": {"images_to_mesh": 43.8}, "load_average": [3.0, 3.0, 3.0]},
        {"scene": "fern", "source": "stereo", "timing": True, "photos": 20, "resolution": [336, 252], "threads": 2,
         "cpu_seconds": {"images_to_mesh": 61.2}, "wall_seconds": 41.5, "load_average": [1.0, 1.0, 1.0]},
    ]
    (tmp_path / "depth_sources.json").write_text(json.dumps({"provenance": prov, "tuning_seconds": 60, "rows": rows}))
    text = section(tmp_path)
    assert "short by 3.00 dB" in text  # fern: 24 - 21
    assert "uncovered 2.0% cost 1.00 dB" in text
    assert "cost 0.50 dB" in text and "depth costs 2.50 dB" in text  # demo: exact - oracle, oracle - best
    assert "| fern | 20 | 336x252 | stereo | 1 | 43.8 | – | 3.0 |" in text  # an older row: no threads, no wall
    assert "| fern | 20 | 336x252 | stereo | 2 | 61.2 | 41.5 | 1.0 |" in text


def test_row_variants_set_the_scoring_and_unknown_ones_fail():
    import pytest

    from bench.depth_sources import scoring

    base = {"nearest": 0, "blend": "network", "angle_sources": (), "fill": "far",  # not finetune's per-scene defaults
            "source_masks": True}
    assert scoring("stereo+fill") == base  # rows without `, nearest K`: the 3 fixed sources
    assert scoring("stereo+fill, sky kept") == base
    assert scoring("stereo+fill, 8 sources") == {**base, "num_views": 8}
    assert scoring("stereo+fill, 8 sources, exposure") == {**base, "num_views": 8,
                                                            "tune": ("encoder", "appearance", "exposure")}
    assert scoring("exact mesh, nearest 6") == {**base, "nearest": 6}
    assert scoring("stereo+fill, nearest 6, angle blend, nearest fill, angle auto, consensus 0.1") == {
        **base, "nearest": 6, "blend": "angle", "fill": "nearest", "angle_sources": (3, 4, 6, 8), "consensus": 0.1}
    assert scoring("stereo+fill, nearest 6, angle blend, no source masks") == {
        **base, "nearest": 6, "blend": "angle", "source_masks": False}
    assert scoring("stereo+fill, all views, match 640") == base  # changes the mesh, not the scoring
    assert scoring("stereo+fill, nearest 6, angle blend, 8 held-out") == {
        **base, "nearest": 6, "blend": "angle", "max_held_out": 8}
    procedural = type("S", (), {"background": (0.0, 0.0, 0.0)})()
    assert scoring("stereo+model", procedural)["fill"] == "background"
    with pytest.raises(ValueError, match="unknown variant"):
        scoring("stereo+fill, 8 views")


def test_nearest_and_all_views_variants():
    """``, nearest K`` scores with ``finetune --nearest K``; ``, all views`` (DTU) meshes every training view, never a
    held-out one."""
    from bench.depth_sources import held_out, scoring
    from omnirecon.engine.protocols import PROTOCOLS

    base = {"blend": "network", "angle_sources": (), "fill": "far", "source_masks": True}
    assert scoring("stereo+fill, nearest 4") == {**base, "nearest": 4}
    assert scoring("stereo+fill, nearest 4, all views") == {**base, "nearest": 4}
    scene = type("S", (), {"splits": {}, "path": "dtu", "__len__": lambda self: 49})()
    targets, few = held_out(scene, PROTOCOLS["dtu"])
    _, every = held_out(scene, PROTOCOLS["dtu"], every_view=True)
    assert len(few) == 14 and len(every) == 41 and set(few) < set(every)
    assert not set(every) & {0, 6, 13, 19, 28, 35, 42, 48} and set(targets) == {0, 13, 35, 48}


def test_a_goal_met_says_so(tmp_path):
    """A best row above its goal reads "met", never "short by" a negative number."""
    from omnirecon.provenance import provenance

    rows = [{"scene": "dtu_scan24", "source": "stereo+fill, nearest 4", "psnr": {"before": 19.0, "after": 19.0},
             "psnr_masked": {"before": 24.5, "after": 24.5}, "coverage": 0.98, "silhouette_iou": 0.98}]
    (tmp_path / "depth_sources.json").write_text(json.dumps({"provenance": provenance(seed=0), "tuning_seconds": 60,
                                                              "rows": rows}))
    text = section(tmp_path)
    assert "met, 2.50 dB over" in text and "short by -" not in text


def test_more_held_out_views_are_reported_beside_the_best(tmp_path):
    """A ``, 8 held-out`` row is never the goal's best (the goal is read on the usual 4 views) but is named beside it,
    with its own gap to the goal."""
    from omnirecon.provenance import provenance

    rows = [{"scene": "dtu_scan37", "source": "stereo+fill", "psnr": {"before": 19.0, "after": None},
             "psnr_masked": {"before": 22.1, "after": None}, "coverage": 0.99},
            {"scene": "dtu_scan37", "source": "stereo+fill, 8 held-out", "psnr": {"before": 18.0, "after": None},
             "psnr_masked": {"before": 21.5, "after": None}, "coverage": 0.99}]
    (tmp_path / "depth_sources.json").write_text(json.dumps({"provenance": provenance(seed=0), "tuning_seconds": 60,
                                                              "rows": rows}))
    text = section(tmp_path)
    assert "best `stereo+fill` 22.10" in text and "met, 0.10 dB over" in text
    assert "on 8 held-out views (`stereo+fill, 8 held-out`) 21.50 → – dB, short by 0.50 dB" in text
