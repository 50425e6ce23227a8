"""The level-of-detail section of BENCHMARKS.md reads only its results JSON: one line per scene and path, the change
in PSNR against the reference row, the load beside each timing."""

import json


def test_section_lists_each_budget_against_the_reference(tmp_path):
    from bench.report.mesh_lod import section
    from omnirecon.provenance import provenance

    assert section(tmp_path) is None  # no results: no section
    base = {"decimate_s": 0.0, "frame_ms": 900.0, "fps": 1.11, "frame_cpu_ms": 300.0, "depth_pass_cpu_ms": 45.0,
            "loadavg_1min": 12.5, "psnr": 22.0, "psnr_loss_db": 0.0}
    rows = [{**base, "face_budget": 0, "frame_grid": 0, "faces": 367249},
            {**base, "face_budget": 200000, "frame_grid": 16, "faces": 200000, "decimate_s": 2.0, "frame_cpu_ms": 180.0,
             "psnr": 21.85, "psnr_loss_db": 0.15, "shader": "gl", "frame_main_cpu_ms": 26.4, "stream_fps": 13.7,
             "stream_cpu_ms": 72.2}]
    scene = {"scene": "fox", "resolution": [225, 400], "rows": rows, "commit": "abc1234"}
    result = {"provenance": provenance(seed=0), "threads": 2, "frames": 10, "realtime_face_budget": 200000,
              "realtime_frame_grid": 16, "machine_note": "shared", "scenes": [scene]}
    (tmp_path / "mesh_lod.json").write_text(json.dumps(result))
    text = section(tmp_path)
    # a row measured before main-thread CPU and streaming were recorded shows "–" there
    assert ("| fox | 225x400 | reference (full mesh, every source) | 367,249 | 900 | 1.1 | 300 | – | – | 45 | 0.0 | "
            "22.00 | +0.00 |") in text
    assert ("| fox | 225x400 | budget 200000, grid 16, gl shader | 200,000 | 900 | 1.1 | 180 | 26 | 13.7 (72) | 45 | 2.0 | "
            "21.85 | -0.15 | 12.5 | `abc1234` |") in text
