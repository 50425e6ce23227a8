"""A ``reconstruct`` that fails keeps what it finished (issue 46): the stages done go into ``OUT.partial``, the error
line names the stage and what is kept, and the next run of the command continues from there; a ``kill -9`` and a
rerun give the output an uninterrupted run gives; a video run prints no ResourceWarning."""

from __future__ import annotations

import json
import os
import shutil
import signal
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import procedural_photos

from bench.resume_kill import start_cli
from omnirecon.data import load_scene
from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.outputs import MARKER, PARTIAL, kept_stages

ROOT = Path(__file__).resolve().parents[2]
CK = ROOT / "checkpoints" / "omnirecon-tiny"
SMALL = ["--resolution", "32", "--mesh-resolution", "32", "--finetune-seconds", "0", "--frames", "2", "--no-viewer",
         "--threads", "1"]
TIMING = ("seconds", "provenance", "peak_rss_mb", "resumed", "fps", "written")
"""Record keys that hold times (or say when and how fast): the only part of an output a rerun may change."""


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """12 procedural frontal views, 128 px, as a folder of photos (no poses): `process` poses them in seconds."""
    return procedural_photos(tmp_path_factory.mktemp("photos"), 128)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _untimed(value):
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items() if not any(t in k for t in TIMING)}
    return [_untimed(v) for v in value] if isinstance(value, list) else value


def _same_output(a: Path, b: Path) -> None:
    """Every file of two reconstruct outputs alike: bytes, JSON records but for their timings; the page only in
    which files it shows (its timings table and FPS differ)."""
    fa, fb = _files(a), _files(b)
    assert sorted(fa) == sorted(fb)
    for name, data in fa.items():
        if name.endswith(".json"):
            assert _untimed(json.loads(data)) == _untimed(json.loads(fb[name])), name
        elif name != "index.html":
            assert data == fb[name], name


@pytest.mark.slow
def test_a_failed_mesh_stage_keeps_the_poses_and_the_rerun_continues(photos, tmp_path, run_cli):
    """The mesh stage fails (the checkpoint's weights are cut short, as by an interrupted copy): one line naming the
    stage, the poses kept in OUT.partial and the previous output untouched; with the checkpoint restored, the same
    command continues from the poses (the scene's files are the very ones the first run wrote) and finishes."""
    pytest.importorskip("pycolmap", reason="pycolmap is the optional `capture` extra")
    ck = tmp_path / "ck"
    shutil.copytree(CK, ck)
    weights = (ck / "model.safetensors").read_bytes()
    (ck / "model.safetensors").write_bytes(weights[:100_000])
    given = _files(photos)
    out = tmp_path / "rec"
    args = ["reconstruct", photos, "--out", out, "--ckpt", ck, *SMALL]
    code, _, err = run_cli(args)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    partial = tmp_path / "rec.partial"
    assert "mesh stage: model.safetensors is unreadable" in err
    assert f"kept in {partial}: the poses; rerun the same command to continue" in err
    assert not out.exists() and (partial / "scene" / "sparse" / "0" / "images.bin").is_file()
    assert sorted(p.name for p in partial.iterdir()) == sorted([PARTIAL, "scene"])  # nothing of the failed stage
    posed = (partial / "scene" / "sparse" / "0" / "images.bin").stat()

    (ck / "model.safetensors").write_bytes(weights)
    code, stdout, err = run_cli(args)
    assert code == 0, err
    assert f"continuing from {partial}: process kept from an earlier run (--no-resume starts over)" in stdout
    record = json.loads((out / "reconstruct.json").read_text())
    assert set(record["resumed"]) == {"process"} and record["resumed"]["process"] > record["seconds"]["process"]
    again = (out / "scene" / "sparse" / "0" / "images.bin").stat()
    assert (again.st_ino, again.st_mtime_ns) == (posed.st_ino, posed.st_mtime_ns)  # the first run's poses, not redone
    assert record["process"]["images_given"] == 12 and (out / "mesh.ply").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ck", "rec"] and not (out / PARTIAL).exists()
    assert _files(photos) == given


def test_changed_options_keep_what_they_do_not_touch(photos, tmp_path):
    """A kept run whose later option changes keeps the stages before it; a changed input starts over; --no-resume
    too. Checked on the record alone (no stage runs here)."""
    from omnirecon.workflows.reconstruct import ReconstructConfig, stage_depends
    from omnirecon.workflows.stages import Stages

    work = tmp_path / "w"
    work.mkdir()
    said = []
    given = shutil.copytree(photos, tmp_path / "photos")
    cfg = ReconstructConfig(path=given, out=tmp_path / "o")
    stages = Stages(work, stage_depends(cfg), say=said.append)
    for name in ("process", "mesh", "finetune"):
        (work / name).mkdir()
        stages.finish(name, {"said": [name]})
    (work / "export").mkdir()  # a stage cut off half-way
    cfg.finetune_seconds = 5.0
    kept = Stages(work, stage_depends(cfg), say=said.append)
    assert list(kept.kept) == ["process", "mesh"] and sorted(p.name for p in work.iterdir()) == sorted(
        [PARTIAL, "process", "mesh"])
    assert said[-1] == f"--finetune-seconds changed since the run that kept {work}: keeping process, mesh, running the rest"
    assert list(Stages(work, stage_depends(cfg), say=said.append).kept) == ["process", "mesh"]
    assert said[-1] == f"continuing from {work}: process, mesh kept from an earlier run (--no-resume starts over)"
    assert Stages(work, stage_depends(cfg), resume=False, say=said.append).kept == {}
    assert "--no-resume" in said[-1] and sorted(p.name for p in work.iterdir()) == [PARTIAL]
    stages = Stages(work, stage_depends(cfg), say=said.append)
    (work / "process").mkdir()
    stages.finish("process", {"said": []})
    os.utime(given / "r_0.png", ns=(0, 0))  # a photo replaced (its time and maybe its size)
    assert Stages(work, stage_depends(cfg), say=said.append).kept == {}
    assert said[-1] == f"PATH's files changed since the run that kept {work}: starting over"


@pytest.mark.slow
def test_kill_9_then_rerun_gives_the_uninterrupted_output(tmp_path, run_cli):
    """``kill -9`` once the mesh stage is kept (fine-tuning or later runs), then the same command: it continues from
    the kept mesh, and every file equals an uninterrupted run's (records but for their timings)."""
    scene = generate_scene(tmp_path / "synth", 0, SynthOptions(rig="object", views=8, resolution=32))
    whole = tmp_path / "whole"
    code, _, err = run_cli(["reconstruct", scene, "--out", whole, *SMALL])
    assert code == 0, err
    out = tmp_path / "rec"
    proc = start_cli(["reconstruct", scene, "--out", out, *SMALL], tmp_path)
    deadline = time.monotonic() + 300
    while "mesh" not in kept_stages(tmp_path / "rec.partial") and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, f"the run ended before its mesh was kept: {proc.communicate()[1][-2000:]}"
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=60)
    assert not out.exists() and kept_stages(tmp_path / "rec.partial")[:2] == ["process", "mesh"]
    code, stdout, err = run_cli(["reconstruct", scene, "--out", out, *SMALL])
    assert code == 0, err
    assert f"continuing from {tmp_path / 'rec.partial'}: process, mesh" in stdout
    assert "mesh" in json.loads((out / "reconstruct.json").read_text())["resumed"]
    _same_output(whole, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec", "synth", "whole"]
    assert (out / MARKER).is_file()


def test_no_depth_names_what_the_source_gave(tmp_path):
    """The fusion's "no depth" error says what the depth source gave and a fix in `omnirecon mesh`'s options; in
    `reconstruct`, the stage, the poses and a fix in its own options (no --depth, no --min-acc)."""
    import torch

    from omnirecon.mesh.build import MeshOptions
    from omnirecon.mesh.confidence import NoDepth, prepare
    from omnirecon.mesh.depth import DepthMaps
    from omnirecon.workflows.reconstruct import ReconstructConfig, failed, stage_depends
    from omnirecon.workflows.stages import Stages

    scene = load_scene(generate_scene(tmp_path / "s", 0, SynthOptions(rig="frontal", views=4, resolution=16)))
    maps = DepthMaps(scene.cameras, torch.zeros(4, 16, 16), torch.zeros(4, 16, 16), [0, 1, 2, 3], {"source": "stereo"})
    with pytest.raises(NoDepth) as e:
        prepare(maps, scene, MeshOptions.preset("fit", depth="stereo"), None)
    assert e.value.one_line() == ("no depth map has a pixel to fuse: stereo gave depth at 0.0% of the pixels (none in "
                                  "4 of 4 maps) (fix: try --depth stereo+model with a checkpoint (--ckpt: a model's "
                                  "depth where stereo finds none), or a larger --resolution)")
    cfg = ReconstructConfig(path=tmp_path / "photos", out=tmp_path / "o", mesh_resolution=64)
    (tmp_path / "o.partial").mkdir()
    stages = Stages(tmp_path / "o.partial", stage_depends(cfg))
    (tmp_path / "o.partial" / "scene").mkdir()  # what process writes
    stages.finish("process", {"processed": {"images_registered": 29, "images_given": 29, "kind": "images"}, "said": []})
    stages.current = "mesh"
    line = failed(cfg, e.value, stages).one_line()
    assert line.startswith(f"{cfg.path}: mesh stage: poses for 29/29 photos; no depth map has a pixel to fuse: stereo "
                           "gave depth at 0.0% of the pixels (none in 4 of 4 maps): likely cause: the photos give "
                           "stereo nothing to match"), line
    assert "raise --mesh-resolution (now 64 px" in line and "--min-acc" not in line and "--depth" not in line
    assert line.endswith(f"kept in {tmp_path / 'o.partial'}: the poses; rerun the same command to continue)")
    stages.finish("process", {"processed": {"images_registered": 40, "images_given": 44, "kind": "video"}, "said": []})
    line = failed(cfg, e.value, stages).one_line()
    assert "poses for 40/44 frames" in line and "walk slower around the subject or raise --fps" in line
    from omnirecon.errors import InputError  # run_mesh's empty mesh, worded for `omnirecon mesh`
    empty = InputError("the mesh is empty: no fused surface survived (see the depth maps and masks)", scene.path,
                       "try a trained checkpoint, more --views, --no-masks or a larger --voxel")
    line = failed(cfg, empty, stages).one_line()
    assert line.startswith(f"{scene.path}: mesh stage: poses for 40/44 frames; the mesh is empty"), line
    assert "raise --mesh-resolution (now 64 px)" in line and "--voxel" not in line and "--views" not in line


@pytest.mark.slow
def test_a_video_run_prints_no_resource_warning(tmp_path, run_cli):
    """A clip in (12 procedural frontal views at 4 fps, as tests/capture/test_process.py's), `reconstruct` to the end
    with ResourceWarning an error around the run: no note of an unclosed pipe (imageio-ffmpeg left ffmpeg's pipes
    open once the video was read to its end)."""
    pytest.importorskip("pycolmap", reason="pycolmap is the optional `capture` extra")
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="videos need the `video` extra")
    from PIL import Image

    ref = generate_scene(tmp_path / "synth", 0, SynthOptions(rig="frontal", views=12, resolution=256))
    clip = tmp_path / "clip.mp4"
    writer = imageio_ffmpeg.write_frames(str(clip), (256, 256), fps=4, quality=10, macro_block_size=16)
    writer.send(None)
    for name in sorted(load_scene(ref).names, key=lambda n: int(Path(n).stem[2:])):  # r_0, r_1, ...: a walk
        writer.send(np.asarray(Image.open(ref / name).convert("RGB")).tobytes())
    writer.close()
    with warnings.catch_warnings():
        warnings.simplefilter("error", ResourceWarning)
        code, _, err = run_cli(["reconstruct", clip, "--out", tmp_path / "rec", "--fps", "4", *SMALL])
    assert code == 0, err
    assert "ResourceWarning" not in err and "note:" not in err, err


def test_a_work_folder_of_the_user_is_never_taken(tmp_path):
    """``OUT.partial`` holding files this tool did not write: refused with one line, its files untouched; a failure
    with nothing kept leaves no work folder, one with a kept stage leaves it (and the previous output) as it was."""
    from omnirecon.errors import InputError
    from omnirecon.outputs import claim, partial_folder
    from omnirecon.workflows.stages import Stages

    out = tmp_path / "rec"
    mine = partial_folder(out)
    mine.mkdir()
    (mine / "notes.txt").write_text("the user's")
    with pytest.raises(InputError, match="work folder holds files this tool did not write"):
        with claim(out, "reconstruct", mode="resume"):
            pass
    assert (mine / "notes.txt").read_text() == "the user's"
    shutil.rmtree(mine)
    with claim(out, "reconstruct", mode="resume") as c:
        (c.work / "old.txt").write_text("a complete earlier run")
    before = _files(out)
    for keep in (False, True):
        with pytest.raises(RuntimeError):
            with claim(out, "reconstruct", mode="resume", overwrite=True, say=lambda s: None) as c:
                stages = Stages(c.work, {"process": {}})
                (c.work / "scene").mkdir()
                if keep:
                    stages.finish("process", {})
                raise RuntimeError("a later stage failed")
        assert _files(out) == before and mine.is_dir() == keep
