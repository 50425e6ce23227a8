"""``reconstruct`` holds its scene and model once (issue 45 item 8): the stages share one ``Capture``, and the scene
folder and the checkpoint are read from disk once however many stages use them."""

from __future__ import annotations

from pathlib import Path

from conftest import procedural_photos

from omnirecon.workflows.reconstruct import ReconstructConfig, run_reconstruct

CK = Path(__file__).resolve().parents[2] / "checkpoints" / "omnirecon-tiny"


def test_scene_and_checkpoint_are_read_once(tmp_path):
    photos = procedural_photos(tmp_path, 96, views=10)
    cfg = ReconstructConfig(path=photos, out=tmp_path / "out", ckpt=CK, resolution=32, mesh_resolution=32,
                            finetune_seconds=0.0, frames=2, viewer=False, threads=1)
    record = run_reconstruct(cfg, say=lambda *a: None)
    # mesh, finetune, export and path read the posed scene at 32 px; every stage used --ckpt (no tuned checkpoint)
    assert record["reads"] == {"scene": 1, "scene_probe": 1, "checkpoint": 1}, record["reads"]
    assert (tmp_path / "out" / "index.html").is_file() and (tmp_path / "out" / "scene" / "process.json").is_file()
    lod = record["path"]["lod"]  # the path's level of detail: measured only below the mesh's own face count
    assert lod["faces"] <= lod["face_budget"] or lod["rows"] == [], lod
