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


def test_section_sets_each_scenes_chosen_level_beside_the_run_before_the_weld(tmp_path):
    """With ``mesh_lod_before_weld.json`` and ``mesh_lod_weld.json`` (the runs before and after the weld) the section
    adds a table of each scene's chosen level before -> after (the chosen level's last row: its sources and stride),
    with the commits of both runs."""
    from bench.report.mesh_lod import section
    from omnirecon.provenance import provenance

    def run(faces: int, fps: float, psnr: float, commit: str) -> dict:
        row = {"face_budget": faces, "frame_grid": 16, "faces": faces, "shader": "gl", "decimate_s": 1.0,
               "frame_ms": 1000 / fps, "fps": fps, "frame_cpu_ms": 60.0, "frame_main_cpu_ms": 20.0, "stream_fps": fps,
               "stream_cpu_ms": 60.0, "depth_pass_cpu_ms": 10.0, "loadavg_1min": 1.2, "psnr": psnr,
               "psnr_loss_db": 22.13 - psnr}
        chosen = {**row, "sources": 3, "weight_stride": 2, "fps": fps + 5}
        scene = {"scene": "fox", "resolution": [225, 400], "rows": [row, chosen], "commit": commit,
                 "lod": {"face_budget": faces, "faces": faces, "sources": 3, "weight_stride": 2, "rows": [],
                         "seconds": 1.0, "tolerance_db": 0.2}}
        return {"provenance": {**provenance(seed=0), "commit": commit}, "threads": 2, "frames": 10,
                "realtime_face_budget": 200000, "realtime_frame_grid": 16, "machine_note": "shared", "scenes": [scene]}

    (tmp_path / "mesh_lod.json").write_text(json.dumps(run(25000, 40.0, 22.0, "now00000000000")))
    (tmp_path / "mesh_lod_weld.json").write_text(json.dumps(run(50000, 27.3, 22.08, "after000000000")))
    assert "before -> after" not in section(tmp_path)
    (tmp_path / "mesh_lod_before_weld.json").write_text(json.dumps(run(100000, 22.3, 21.99, "before00000000")))
    text = section(tmp_path)
    assert "The same bench at commit `before000000`" in text and "beside the run at commit `after0000000`" in text
    assert "- fox: 45.0 FPS, streamed 40.0 FPS, -0.13 dB against the full mesh (met)" in text  # the goal, last row
    assert ("| fox | 100,000 faces, 3 sources, MLP every 2 px -> 50,000 faces, 3 sources, MLP every 2 px | 27.3 -> 32.3 "
            "| 22.3 -> 27.3 | 60 -> 60 | 21.99 -> 22.08 | -0.14 -> -0.05 |") in text


def test_section_sets_the_photographed_faces_beside_the_same_level_with_all_its_faces(tmp_path):
    """A scene whose chosen level draws only the faces the photos see: its row says so, and a table sets it beside the
    row of the same budget, grid, sources and stride with all its faces (not beside another budget's row)."""
    from bench.report.mesh_lod import section
    from omnirecon.provenance import provenance

    def row(budget: int, faces: int, fps: float, psnr: float, **extra) -> dict:
        return {"face_budget": budget, "frame_grid": 16, "faces": faces, "shader": "gl", "decimate_s": 1.0,
                "frame_ms": 1000 / fps, "fps": fps, "frame_cpu_ms": 1000 / fps * 1.5, "frame_main_cpu_ms": 9.0,
                "stream_fps": fps, "stream_cpu_ms": 60.0, "depth_pass_cpu_ms": faces / 1000, "loadavg_1min": 1.5,
                "psnr": psnr, "psnr_loss_db": 14.48 - psnr, **extra}

    rows = [row(0, 191977, 10.0, 14.48), row(25000, 25000, 20.0, 14.60),
            row(25000, 25000, 26.0, 14.93, sources=3, weight_stride=2),
            row(25000, 8275, 32.0, 14.91, sources=3, weight_stride=2, photographed=True)]
    scene = {"scene": "lund", "resolution": [512, 383], "rows": rows, "commit": "abc1234",
             "lod": {"face_budget": 25000, "faces": 7982, "sources": 3, "weight_stride": 2, "photographed": True,
                     "rows": [{"budget": 25000, "faces": 7982, "sources": 3, "weight_stride": 2, "photographed": True,
                               "psnr": 17.02}], "seconds": 1.0, "tolerance_db": 0.2}}
    (tmp_path / "mesh_lod.json").write_text(json.dumps({
        "provenance": provenance(seed=0), "threads": 2, "frames": 10, "realtime_face_budget": 200000,
        "realtime_frame_grid": 16, "machine_note": "shared", "scenes": [scene]}))
    text = section(tmp_path)
    assert "| lund | 512x383 | budget 25000, grid 16, gl shader, 3 sources per frame, MLP every 2 px, only the faces the photos see | 8,275 |" in text
    assert "| lund | 25,000 -> 8,275 | 26.0 -> 32.0 | 26.0 -> 32.0 | 58 -> 47 | 25 -> 8 | 14.93 -> 14.91 |" in text
    assert "7,982 faces x 3 sources, MLP every 2 px, photographed only 17.02" in text
    assert "**7,982 faces, 3 sources per frame, the MLP every 2 px, only the faces the photos see**" in text
    assert "- lund: 32.0 FPS, streamed 32.0 FPS, +0.43 dB against the full mesh (met)" in text


def test_rows_of_other_candidate_counts_are_labelled_and_not_what_the_videos_draw(tmp_path):
    """``--proposed`` rows (the chosen level with other counts of candidates per grid point) carry their count in the
    table; the goal line still reads the chosen level's own row, which comes before them."""
    from bench.report.mesh_lod import section
    from omnirecon.provenance import provenance

    row = {"face_budget": 50000, "frame_grid": 16, "faces": 50000, "shader": "gl", "decimate_s": 1.0, "frame_ms": 40.0,
           "fps": 25.0, "frame_cpu_ms": 60.0, "frame_main_cpu_ms": 20.0, "stream_fps": 26.0, "stream_cpu_ms": 60.0,
           "depth_pass_cpu_ms": 10.0, "loadavg_1min": 1.2, "psnr": 22.08, "psnr_loss_db": 0.05, "candidates_proposed": 3}
    other = {**row, "fps": 35.0, "stream_fps": 36.0, "psnr": 21.9, "psnr_loss_db": 0.23, "proposed": 0,
             "candidates_proposed": 0}
    scene = {"scene": "fox", "resolution": [225, 400], "rows": [row, other], "commit": "abc1234",
             "setting": {"blend": "angle"},
             "lod": {"face_budget": 50000, "faces": 50000, "sources": None, "weight_stride": 1, "rows": [],
                     "seconds": 1.0, "tolerance_db": 0.2}}
    result = {"provenance": provenance(seed=0), "threads": 2, "frames": 10, "realtime_face_budget": 200000,
              "realtime_frame_grid": 16, "machine_note": "shared", "scenes": [scene]}
    (tmp_path / "mesh_lod.json").write_text(json.dumps(result))
    text = section(tmp_path)
    assert "| fox | 225x400 | budget 50000, grid 16, gl shader, 0 candidates proposed per grid point | 50,000 |" in text
    assert "| fox | 225x400 | budget 50000, grid 16, gl shader | 50,000 |" in text
    assert "- fox: 25.0 FPS, streamed 26.0 FPS, -0.05 dB against the full mesh (short)" in text
    scene["record"], scene["setting"] = "fox/finetune/curve.json", {"blend": "angle", "angle_sources": 8}
    (tmp_path / "mesh_lod.json").write_text(json.dumps(result))
    assert ("- fox: 25.0 FPS, streamed 26.0 FPS, -0.05 dB against the full mesh (short; finetune's record: angle "
            "blend, 8 sources per point)") in section(tmp_path)
