"""`reconstruct`'s work folder and stage errors under hostile leftovers (issue 46 item 4): a kept record that is garbage
is read as nothing kept; a record folder that is a link to elsewhere is refused (the user's files there stay); a
process-stage error on a photo folder names the photo (it was replaced by "no supported scene format")."""

from __future__ import annotations

import json

import pytest

from omnirecon.errors import InputError
from omnirecon.outputs import PARTIAL, claim, partial_folder


@pytest.mark.parametrize("text", ["{{{", "[" * 50_000 + "]" * 50_000, '{"stages": [1, 2]}', '{"stages": {"process": 3}}'])
def test_a_garbage_record_keeps_nothing(tmp_path, text):
    from omnirecon.outputs import kept_stages
    from omnirecon.workflows.stages import Stages

    work = tmp_path / "w"
    (work / PARTIAL).mkdir(parents=True)
    (work / PARTIAL / "stages.json").write_text(text)
    (work / "scene").mkdir()  # a stage's leftovers: removed, nothing of them kept
    assert kept_stages(work) in ([], ["process"])
    stages = Stages(work, {"process": {"PATH's files": "x"}}, say=lambda s: None)
    assert stages.kept == {} and sorted(p.name for p in work.iterdir()) == [PARTIAL]
    assert json.loads((work / PARTIAL / "stages.json").read_text()) == {"stages": {}}


def test_a_record_folder_linking_elsewhere_is_refused_and_its_target_kept(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("the user's")
    work = partial_folder(tmp_path / "rec")
    work.mkdir()
    (work / PARTIAL).symlink_to(mine)
    with pytest.raises(InputError, match=r"rec.partial exists and is not a folder \(or its .omnirecon-partial is a link"):
        with claim(tmp_path / "rec", "reconstruct", mode="resume"):
            pass
    assert [p.name for p in mine.iterdir()] == ["notes.txt"] and (work / PARTIAL).is_symlink()


def test_a_broken_photo_is_named_in_the_process_stage(tmp_path, run_cli):
    """A truncated JPEG among the photos: the line names it and the stage; no output, no work folder."""
    import numpy as np
    from PIL import Image

    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(4):
        Image.fromarray((np.random.default_rng(i).random((40, 40, 3)) * 255).astype(np.uint8)).save(photos / f"p{i}.jpg")
    data = (photos / "p0.jpg").read_bytes()
    (photos / "p9.jpg").write_bytes(data[: len(data) // 2])
    code, _, err = run_cli(["reconstruct", photos, "--out", tmp_path / "rec", "--threads", "1", "--no-viewer"])
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"omnirecon: error: {photos / 'p9.jpg'}: process stage: cannot read image file"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]


def test_eval_on_images_smaller_than_ssims_window_is_one_line(tmp_path, run_cli):
    from tests.data.test_bad_input import blender_scene

    scene = blender_scene(tmp_path / "scene")
    train = json.loads((scene / "transforms_train.json").read_text())
    (scene / "transforms_test.json").write_text(json.dumps(train))  # a test split: the protocol's targets
    code, _, err = run_cli(["eval", "--model", "floor", "--scenes", scene, "--out", tmp_path / "ev", "--threads", "1"])
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "images are 8x8 px, smaller than SSIM's 11 px window" in err and str(scene) in err
    assert not (tmp_path / "ev").exists()
