"""``omnirecon process`` under hostile captures: photos too small for SfM are refused before pycolmap sees them,
a native crash of pycolmap is one error line (its process is a child), and a video's ``--fps`` is capped at
the clip's own rate and blamed when it samples no frame (issue 46 item 4)."""

import sys

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("pycolmap", reason="pycolmap is the optional `capture` extra: pip install pycolmap")

from omnirecon.capture.colmap_sfm import SfmOptions  # noqa: E402
from omnirecon.capture.images import stage_images  # noqa: E402
from omnirecon.capture.process import MIN_SIDE, process, sample_rate, sfm_in_child  # noqa: E402
from omnirecon.capture.video import sample_frames  # noqa: E402
from omnirecon.errors import InputError  # noqa: E402


def photos(folder, side: int, n: int = 4):
    folder.mkdir()
    for i in range(n):
        noise = (np.random.default_rng(i).random((side, side, 3)) * 255).astype(np.uint8)
        Image.fromarray(noise).save(folder / f"p{i}.png")
    return folder


@pytest.mark.parametrize("side", [1, 8])
def test_photos_too_small_to_match_are_refused_before_sfm(tmp_path, side):
    src = photos(tmp_path / "tiny", side)
    with pytest.raises(InputError) as e:
        process(src, tmp_path / "out", quiet=True)
    assert str(src / "p0.png") in str(e.value) and f"at least {MIN_SIDE} px" in str(e.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny"]  # no out, no work folder, no lock


def test_a_native_crash_of_pycolmap_is_one_error_not_the_end_of_the_command(tmp_path):
    """1-pixel photos given to pycolmap directly (past the size check) kill its process with a signal: here
    that process is a child, and the crash comes back as an InputError naming the input."""
    src = photos(tmp_path / "tiny", 1)
    staged = stage_images(src, tmp_path / "work" / "input", min_images=3)
    args = (staged.folder, staged.names, tmp_path / "work", SfmOptions(), False, src, None, tmp_path / "scene",
            None, True, None)
    with pytest.raises(InputError) as e:
        sfm_in_child(src, args)
    assert "crashed (SIG" in str(e.value) and str(src) in str(e.value), e.value


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A 3 s clip at 4 frames per second (12 distinct frames, 64x64)."""
    import imageio_ffmpeg

    path = tmp_path_factory.mktemp("clip") / "clip.mp4"
    writer = imageio_ffmpeg.write_frames(str(path), (64, 64), fps=4, quality=8, macro_block_size=16)
    writer.send(None)
    for i in range(12):
        writer.send((np.random.default_rng(i).random((64, 64, 3)) * 255).astype(np.uint8).tobytes())
    writer.close()
    return path


def test_fps_above_the_clips_rate_samples_each_frame_once(clip, tmp_path):
    said = []
    rate = sample_rate(clip, 240.0, say=said.append)
    assert rate == pytest.approx(4.0) and len(said) == 1 and "--fps 240" in said[0], said
    assert len(sample_frames(clip, tmp_path / "f", rate)) == 12  # not 300 repeated frames
    assert sample_rate(clip, 2.0, say=said.append) == 2.0 and len(said) == 1


def test_an_fps_that_samples_no_frame_is_blamed_on_the_option(clip, tmp_path):
    with pytest.raises(InputError) as e:
        process(clip, tmp_path / "out", fps=1e-30, quiet=True)
    assert "--fps" in str(e.value) and str(clip) not in str(e.value), e.value
    assert list(tmp_path.iterdir()) == []


def _clip(path, frames: int, side: int = 64):
    import imageio_ffmpeg

    writer = imageio_ffmpeg.write_frames(str(path), (side, side), fps=4, quality=8, macro_block_size=1)
    writer.send(None)
    for i in range(frames):
        writer.send((np.random.default_rng(i).random((side, side, 3)) * 255).astype(np.uint8).tobytes())
    writer.close()
    return path


def test_a_clip_too_short_to_pose_gets_video_advice(tmp_path):
    """A one-frame clip: named, told to record longer (not "add more photos", not "use --fps of at least 4, e.g. 2")."""
    clip = _clip(tmp_path / "one.mp4", 1)
    with pytest.raises(InputError) as e:
        process(clip, tmp_path / "out", quiet=True)
    assert str(clip) in str(e.value) and "holds 1 frame" in str(e.value) and "record a clip" in str(e.value), e.value
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one.mp4"]


def test_an_fps_that_samples_under_three_frames_names_the_clip_and_the_option(clip, tmp_path):
    """--fps 0.5 on a 3 s clip samples 2 frames: the clip and --fps are named (not the work folder's frames)."""
    with pytest.raises(InputError) as e:
        process(clip, tmp_path / "out", fps=0.5, quiet=True)
    assert str(e.value).startswith(f"{clip}: --fps 0.5 samples 2 frames") and "raise --fps" in str(e.value), e.value
    assert list(tmp_path.iterdir()) == []


def test_frames_too_small_to_match_are_refused_before_sfm(tmp_path):
    """A clip of 8x8 frames: refused naming the clip before pycolmap runs (it crashed on them)."""
    clip = _clip(tmp_path / "tiny.mp4", 12, side=8)
    with pytest.raises(InputError) as e:
        process(clip, tmp_path / "out", fps=4, quiet=True)
    assert str(clip) in str(e.value) and "frames are 8x8 pixels" in str(e.value) and "crashed" not in str(e.value)


def test_an_all_black_mask_is_named(tmp_path):
    """A mask with no white pixel would leave its photo without a feature: refused naming the mask, not answered
    "take more overlapping photos" after SfM."""
    from omnirecon.capture.images import stage_masks

    src = photos(tmp_path / "p", 32)
    masks = tmp_path / "m"
    masks.mkdir()
    for i in range(4):
        Image.fromarray(np.full((32, 32), 255 * (i != 2), np.uint8)).save(masks / f"p{i}.png")
    staged = stage_images(src, tmp_path / "staged")
    with pytest.raises(InputError) as e:
        stage_masks(masks, staged, tmp_path / "staged_masks")
    assert str(e.value).startswith(f"{masks / 'p2.png'}: the mask is all black"), e.value


def _descendants(pid: int) -> dict[int, int]:
    """``{process: its parent}`` of the processes below ``pid`` (its children, theirs, ...): multiprocessing's fork
    server and resource tracker, and the SfM child the server forked."""
    from pathlib import Path

    parent = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            parent[int(stat.parent.name)] = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
    out, frontier = {}, {pid}
    while frontier:
        frontier = {c for c, p in parent.items() if p in frontier}
        out.update({c: parent[c] for c in frontier})
    return out


def _alive(pid: int) -> bool:
    from pathlib import Path

    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's")
def test_a_killed_process_leaves_no_sfm_child(tmp_path):
    """`process` killed with SIGKILL while pycolmap runs in its child: the child ends with it (it went on writing into
    the killed run's work folder until SfM finished)."""
    import os
    import subprocess
    import time
    from pathlib import Path

    from conftest import procedural_photos

    photos = procedural_photos(tmp_path, 128)  # 12 views: SfM runs for several seconds
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2]), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "omnirecon.cli", "process", str(photos), "--out",
                             str(tmp_path / "out"), "--threads", "1", "--quiet"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob(".out.*/database.db")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)  # until pycolmap is at work (its feature database made)
    below = _descendants(proc.pid)
    sfm = [c for c, p in below.items() if p != proc.pid]  # forked by the server: the child running pycolmap
    assert sfm, f"no SfM child seen (process exit {proc.poll()})"
    proc.kill()
    proc.wait()
    for procs, seconds in ((sfm, 2), (list(below), 30)):  # the server and the tracker end in turn (interpreter exit)
        deadline = time.monotonic() + seconds
        while any(_alive(c) for c in procs) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(_alive(c) for c in procs), [Path(f"/proc/{c}/cmdline").read_bytes()[:120] for c in procs
                                                   if _alive(c)]


def test_a_clip_is_never_sampled_again_above_its_own_rate(clip, tmp_path):
    """Noise frames of a 4 fps clip at --fps 240 (so at 4): no second pass at 12 fps (it staged each frame three
    times); the line says every frame was sampled and advises a higher frame rate, not more --fps."""
    with pytest.raises(InputError) as e:
        process(clip, tmp_path / "out", fps=240, quiet=True)
    line = str(e.value)
    assert "of 12 video frames registered at 4 fps" in line and "every frame of the clip was sampled" in line, line
    assert "sampled again" not in line and "record at a higher frame rate" in line and "--fps (up to" not in line


def test_visual_words_of_alike_frames_warn_nothing():
    """Few, identical descriptors leave k-means clusters empty: harmless (such a word is never counted), and no
    scipy warning reaches the user."""
    import warnings

    from omnirecon.capture.retrieval import word_histograms

    rng = np.random.default_rng(0)
    same = rng.random((1, 128)).astype(np.float32).repeat(40, 0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        hist = word_histograms([same, same, same], words=8)
    assert hist.shape == (3, 8) and np.isfinite(hist).all()
