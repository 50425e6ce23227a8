"""Videos: when too few frames register, the tool samples more densely and matches in sequence with loop
detection before giving up; the error then names what was tried and what the user can do.

The clip is the 12 views of a procedural capture (``omnirecon synth``, frontal rig, 256 px) at 4 frames per
second (3 s). Sampled at 1 fps its 3 frames are 40 degrees of arc apart and none registers (measured:
0 of 3); the second pass samples 3 fps (9 frames) and registers all 9.
"""

import shutil

import numpy as np
import pytest
from PIL import Image

pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is the optional `capture` extra: pip install pycolmap")
imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="the optional `video` extra")

from conftest import procedural_photos  # noqa: E402

from omnirecon.capture.process import process, summary_lines  # noqa: E402
from omnirecon.capture.retrieval import nearest_pairs, word_histograms  # noqa: E402
from omnirecon.capture.video import video_duration  # noqa: E402
from omnirecon.cli import main  # noqa: E402
from omnirecon.data import load_scene  # noqa: E402
from omnirecon.data.synth.generate import SynthOptions, generate_scene  # noqa: E402


def write_clip(path, frames, fps: float) -> None:
    """``frames`` (H, W, 3 uint8 arrays) as an H.264 clip at ``fps``."""
    h, w = frames[0].shape[:2]
    writer = imageio_ffmpeg.write_frames(str(path), (w, h), fps=fps, quality=10, macro_block_size=16)
    writer.send(None)
    for f in frames:
        writer.send(np.ascontiguousarray(f).tobytes())
    writer.close()


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    root = tmp_path_factory.mktemp("clip")
    ref_dir = generate_scene(root / "synth", 0, SynthOptions(rig="frontal", views=12, resolution=256))
    frames = [np.asarray(Image.open(ref_dir / n).convert("RGB")) for n in load_scene(ref_dir).names]
    path = root / "walk.mp4"
    write_clip(path, frames, 4)
    shutil.rmtree(root / "synth")
    return path


def test_too_few_frames_trigger_the_denser_pass(clip, tmp_path):
    assert abs(video_duration(clip) - 3.0) < 0.1
    out = tmp_path / "scene"
    s = process(clip, out, fps=1, quiet=True)
    first, second = s["video_passes"]
    assert first["fps"] == 1 and first["frames"] == 3 and first["registered"] < 3
    assert second["fps"] == 3 and second["frames"] == 9 and second["loop_pairs"] == 5
    assert s["images_given"] == 9 and s["images_registered"] == second["registered"] >= 8 and s["fps"] == 3
    assert len(load_scene(out)) == s["images_registered"]
    assert any(line.startswith("video: ") and "sampled again at 3 fps" in line for line in summary_lines(s))


def test_one_pass_when_enough_frames_register(clip, tmp_path):
    s = process(clip, tmp_path / "scene", fps=4, quiet=True)
    assert len(s["video_passes"]) == 1 and s["images_registered"] >= 11


def refused(capsys, tmp_path, source, *args):
    out = tmp_path / "out_scene"
    code = main(["process", str(source), "--out", str(out), "--quiet", *map(str, args)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert not out.exists()
    return err


def test_video_failure_names_what_was_tried(capsys, tmp_path):
    """Frames of noise never register: both passes are named, and what to do (slower, light, --fps)."""
    rng = np.random.default_rng(0)
    noise = tmp_path / "noise.mp4"
    write_clip(noise, [rng.integers(0, 256, (128, 128, 3), dtype=np.uint8) for _ in range(6)], 2)
    err = refused(capsys, tmp_path, noise, "--fps", 1)
    assert "video frames registered at 1 fps" in err and "sampled again at 2 fps" in err, err  # the clip's own rate
    assert "loop detection" in err and "walk more slowly" in err and "light" in err, err
    assert "record at a higher frame rate" in err and "--fps (up to" not in err, err  # every frame was sampled
    assert "add photos" not in err
    err = refused(capsys, tmp_path, noise, "--fps", 1, "--max-frames", 3)  # 3 s: no room for more frames
    assert "--max-frames 3 leaves no room" in err, err


def test_retrieval_finds_the_loop():
    """Ten images of random words; the last shows what the first showed: its loop pair is found."""
    rng = np.random.default_rng(1)
    base = [rng.normal(size=(300, 128)).astype(np.float32) for _ in range(10)]
    base[9] = base[0] + 0.05 * rng.normal(size=(300, 128)).astype(np.float32)
    hist = word_histograms([d / np.linalg.norm(d, axis=1, keepdims=True) for d in base], words=64)
    pairs = nearest_pairs(hist @ hist.T, per_image=1, skip=3)
    assert (0, 9) in pairs and all(j - i > 3 for i, j in pairs)


def test_loop_pairs_from_a_real_database(tmp_path):
    """Sequential matching of 12 procedural views with 2 neighbours each plus 2 loop pairs per image from
    the database's own SIFT words: more pairs than sequential alone, all images registered."""
    from omnirecon.capture.colmap_sfm import SfmOptions, Stages, run_sfm
    from omnirecon.capture.images import stage_images
    from omnirecon.capture.retrieval import image_pairs, similar_pairs

    photos = procedural_photos(tmp_path, 256)
    staged = stage_images(photos, tmp_path / "input", min_images=3, shared_camera=True)
    options = SfmOptions(matcher="sequential", overlap=2, loop_pairs=2, learned="off")
    with Stages(quiet=True) as stages:
        result = run_sfm(staged.folder, staged.names, tmp_path / "work", options, stages)
    loops = similar_pairs(tmp_path / "work" / "database.db", staged.names, 2, 2)
    assert loops and all(j - i > 2 for i, j in loops)
    assert result.pairs == len(set(image_pairs(12, True, 2)) | set(loops)) > len(image_pairs(12, True, 2))
    assert len(result.registered) == 12
