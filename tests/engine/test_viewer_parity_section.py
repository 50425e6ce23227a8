"""The viewer-parity section of BENCHMARKS.md reads only its results JSON."""

import json


def test_section_lists_the_setting_the_bundle_and_both_scores(tmp_path):
    from bench.report.viewer_parity import section
    from omnirecon.provenance import provenance

    assert section(tmp_path) is None  # no results: no section
    setting = {"blend": "angle", "fill": "nearest", "sources": 0, "angle_sources": 4, "source_masks": True, "cracks": 2}
    row = {"scene": "dtu_scan37", "held_out": [0, 6], "resolution": [400, 300], "setting": setting,
           "bundle": {"version": 2, "sources": 41, "megabytes": 61.5}, "python": 18.9, "browser": 18.8,
           "python_masked": 21.41, "browser_masked": 21.38, "parity": 40.12, "max_diff": 97,
           "mean_diff": 0.31, "browser_ms_per_frame": 1500.0, "browser_cpu_ms_per_frame": 1700.0, "python_cpu_ms_per_frame": 240.0, "load_average": [3.0],
           "scored_by": "objects", "browser_off": [{"off": "source masks", "psnr": 18.7, "psnr_masked": 21.2},
                                                   {"off": "nearest fill", "psnr": 18.0, "psnr_masked": 21.0}]}
    (tmp_path / "viewer_parity.json").write_text(json.dumps({"provenance": provenance(seed=0), "rows": [row]}))
    text = section(tmp_path)
    assert "without source masks 21.20 -> without nearest fill 21.00" in text
    assert ("| dtu_scan37 (2 views, 400x300) | angle (every training view, 4 per point, source masks), nearest fill, "
            "cracks 2 | v2, 41 sources, 61.5 MB | 21.41 | 21.38 | 40.12 | 97 / 0.31 | 1500 / 1700 | 240 | 3.0 |") in text
    tuned = {**row, "scene": "lund", "tuned": True, "commit": "0123456789abcdef", "scored_by": "image",
             "setting": {**setting, "blend": "network", "sources": 6}, "browser_off": []}
    (tmp_path / "viewer_parity.json").write_text(json.dumps({"provenance": provenance(seed=0), "rows": [row, tuned]}))
    assert ("| lund (2 views, 400x300) | network (6 sources per frame), nearest fill, cracks 2 | v2, 41 sources, 61.5 MB, "
            "tuned weights | 18.90 | 18.80 | 40.12 | 97 / 0.31 | 1500 / 1700 | 240 | 3.0 | `0123456789ab` |") in section(tmp_path)
    gaps = {"scene": "dtu_scan37", "gaps": [{"rung": "main's viewer", "psnr": 10.8, "psnr_masked": 14.06},
                                            {"rung": "every training view", "psnr": 18.3, "psnr_masked": 21.06}]}
    (tmp_path / "viewer_parity_gaps.json").write_text(json.dumps({"provenance": provenance(seed=0), "rows": [gaps]}))
    assert "| dtu_scan37 | main's viewer 14.06 -> every training view 21.06 |" in section(tmp_path)
