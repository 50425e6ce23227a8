"""The surface-tuning section of BENCHMARKS.md reads only its results JSON: per scene and row, the held-out PSNR at
each budget, the moved mesh rasterized afresh, the offsets against their bound and the load."""

import json


def test_section_lists_each_row_with_its_curve_and_moved_mesh(tmp_path):
    from bench.report.finetune_surface import section
    from omnirecon.provenance import provenance

    assert section(tmp_path) is None  # no results: no section
    curve = [{"seconds": t, "psnr": p} for t, p in ((0.0, 27.02), (10.0, 27.1), (30.0, 27.3), (60.0, 27.35))]
    row = {"row": "surface_grid32", "blend": "network", "curve": curve, "returned_from": {"seconds": 30.0},
           "after_rerasterized": {"psnr": 27.31}, "surface": {"mean_abs_offset": 0.0012, "bound": 0.035},
           "steps": 400, "load_average": {"start": 9.5, "end": 12.25}, "provenance": {"commit": "abc1234"},
           "mesh_note": "stereo at 128 px"}
    (tmp_path / "finetune_surface.json").write_text(json.dumps({"provenance": provenance(seed=0),
                                                                 "rows": {"demo/surface_grid32": row}}))
    text = section(tmp_path)
    assert ("| demo | `--tune surface --surface-res 32`: offsets from a 32³ grid sampled at the vertices | network | "
            "27.02 | 27.10 | 27.30 | 27.35 | 30 | 27.31 | 0.0012 / 0.035 | 400 | 9.5–12.2 | `abc1234` |") in text
    assert "Meshes, demo: stereo at 128 px" in text
