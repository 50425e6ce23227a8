"""The real-time blend section of BENCHMARKS.md reads only its results JSON."""

import json


def test_section_lists_each_setting_beside_finetunes_score(tmp_path):
    from bench.report.realtime_blend import section
    from omnirecon.provenance import provenance

    assert section(tmp_path) is None  # no results: no section
    setting = {"blend": "angle", "fill": "nearest", "sources": 41, "angle_sources": 4, "source_masks": True}
    before = {**setting, "sources": 3, "angle_sources": 6, "source_masks": False}
    row = {"scene": "dtu_scan37", "finetune_record": {"psnr": 19.67, "psnr_masked": 22.02}, "load_average": [2.0],
           "before": {"setting": before, "psnr": 19.0, "psnr_masked": 21.19, "cpu_ms_per_frame": 66.0},
           "finetune": {"setting": setting, "psnr": 19.6, "psnr_masked": 22.04, "cpu_ms_per_frame": 360.0}}
    prov = provenance(seed=0)
    (tmp_path / "realtime_blend.json").write_text(json.dumps({"provenance": prov, "rows": [row]}))
    text = section(tmp_path)
    assert "| dtu_scan37 | 22.02 | angle (3 sources per frame, 6 per point), nearest fill | 21.19 | 66 |" in text
    assert "| angle (41 sources per frame, 4 per point, source masks), nearest fill | 22.04 | 360 | 2.0 |" in text
