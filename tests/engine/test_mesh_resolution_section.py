"""The Mesh resolution section: one row per scene and meshing side, the photos' side marked."""

from __future__ import annotations

import json

from bench.report.mesh_resolution import section


def test_section_lists_each_side_and_marks_the_photos_one(tmp_path):
    from omnirecon.provenance import provenance

    assert section(tmp_path) is None  # no results: no section
    row = {"scene": "fern", "depth": "stereo", "faces": 199_999, "photo_side": 336, "coverage": 1.0,
           "load_average": [3.2, 3.0, 3.0]}
    rows = [{**row, "mesh_side": 128, "mesh_resolution": [128, 96], "mesh_cpu_seconds": 9.5, "psnr": 21.0,
             "psnr_covered": 21.0},
            {**row, "mesh_side": 336, "mesh_resolution": [336, 252], "mesh_cpu_seconds": 40.25, "psnr": 23.92,
             "psnr_covered": 23.92, "psnr_masked": 22.5}]
    (tmp_path / "mesh_resolution.json").write_text(json.dumps({"provenance": provenance(seed=0), "rows": rows}))
    text = section(tmp_path)
    assert "| fern | 128x96 | stereo | 199,999 | 9.5 | 21.00 | – | 21.00 | 100.0% | 3.2 |" in text
    assert "| fern | 336x252 (photos) | stereo | 199,999 | 40.2 | 23.92 | 22.50 | 23.92 | 100.0% | 3.2 |" in text
