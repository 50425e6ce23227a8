"""``omnirecon process``: camera poses from photos or a video with COLMAP (pycolmap), and its bad input.

The capture is a 12-view procedural scene (``omnirecon synth``, DTU-like frontal rig, 256 px) with
its poses dropped: only the RGB files go in. Tolerance after a similarity alignment to the true
poses: every view registered, median rotation error below 1 degree (max below 2), camera centres
within 1% of the scene extent (median) and 2% (max). Measured: 0.24 / 0.53 degrees, 0.13 / 0.35%.
"""

import shutil

import numpy as np
import pytest
import torch

pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is the optional `capture` extra: pip install pycolmap")

from omnirecon.capture.align import pose_errors, umeyama  # noqa: E402
from omnirecon.capture.colmap_sfm import SfmOptions  # noqa: E402
from omnirecon.capture.images import stage_images  # noqa: E402
from omnirecon.capture.process import process  # noqa: E402
from omnirecon.capture.retrieval import image_pairs  # noqa: E402
from omnirecon.cli import main  # noqa: E402
from omnirecon.data import ReadOptions, load_scene  # noqa: E402
from omnirecon.data.synth.generate import SynthOptions, generate_scene  # noqa: E402
from omnirecon.errors import InputError  # noqa: E402

VIEWS = 12


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """``(photos folder, reference scene)``: the synth views' RGB files r_0.png ... r_11.png only."""
    root = tmp_path_factory.mktemp("capture")
    ref_dir = generate_scene(root / "synth", 0, SynthOptions(rig="frontal", views=VIEWS, resolution=256))
    ref = load_scene(ref_dir)
    photos = root / "photos"
    photos.mkdir()
    for name in ref.names:
        shutil.copyfile(ref_dir / name, photos / name.split("/")[-1])
    return photos, ref


@pytest.fixture(scope="module")
def processed(capture, tmp_path_factory):
    photos, _ = capture
    out = tmp_path_factory.mktemp("proc") / "scene"
    summary = process(photos, out, quiet=True)
    return out, summary


def errors_against(scene, ref, order=None):
    """Pose errors of ``scene`` (in COLMAP's frame) against ``ref``, views matched by name (or by
    ``order``: the index in ``ref`` of each of ``scene``'s views)."""
    names = [n.split("/")[-1] for n in ref.names]
    idx = order if order is not None else [names.index(n.split("/")[-1]) for n in scene.names]
    extent = float((ref.bounds[1] - ref.bounds[0]).double().norm())
    est = scene.cameras.transformed(scene.to_input).c2w.numpy()
    return pose_errors(est, ref.cameras.c2w[idx].numpy(), extent)


def test_process_recovers_poses(capture, processed):
    _, ref = capture
    out, summary = processed
    assert summary["images_registered"] == VIEWS and summary["images_given"] == VIEWS and summary["models"] == 1
    assert summary["points3D"] > 50 and summary["mean_reprojection_error_px"] < 1.0
    assert set(summary["seconds"]) >= {"features", "matching", "mapping", "undistort", "total"}
    # the SfM child's own CPU seconds (not the process's: the stage clocks add them): at least its mapping's share
    assert summary["sfm_cpu_seconds"] > 0.2 * summary["seconds"]["mapping"], summary
    scene = load_scene(out)
    assert scene.format == "colmap" and len(scene) == VIEWS
    e = errors_against(scene, ref)
    assert e["rotation_deg_median"] < 1.0 and e["rotation_deg_max"] < 2.0, e
    assert e["centre_pct_median"] < 1.0 and e["centre_pct_max"] < 2.0, e
    # the scene frame is upright: the synth world is z-up, and so is ours after the alignment's rotation
    R = np.array(e["similarity"]["rotation"])  # reference <- COLMAP
    T = scene.to_input.numpy()
    up_ref = R @ (T[:3, :3] @ np.array([0, 0, 1.0]))
    assert up_ref[2] / np.linalg.norm(up_ref) > np.cos(np.radians(10))


def test_scene_layout_and_frames(processed):
    """images_2 / images_4 are read for downscale 2 / 4; to_input maps back to the written COLMAP model."""
    out, _ = processed
    for f in (2, 4):
        assert len(list((out / f"images_{f}").iterdir())) == VIEWS
    full = load_scene(out)
    half = load_scene(out, options=ReadOptions(downscale=2))
    assert half.meta["image_folder"] == "images_2" and half.width == round(full.width / 2)
    assert torch.allclose(half.cameras.fx, full.cameras.fx * half.width / full.width)
    rec = pycolmap.Reconstruction(out / "sparse" / "0")
    assert all(c.model_name == "PINHOLE" for c in rec.cameras.values()) and rec.num_cameras() == 1
    back = full.cameras.transformed(full.to_input)
    for i, name in enumerate(full.names):
        im = rec.find_image_with_name(name.split("/")[-1])
        assert np.allclose(back.centers[i].numpy(), im.projection_center(), atol=1e-6)
    # normalised: the bounds box has half-diagonal ~1 and is centred near 0 (5% padding)
    assert abs(float((full.bounds[1] - full.bounds[0]).norm()) / 2 - 1.1) < 0.05
    assert full.bounds.mean(0).abs().max() < 1e-4


def test_video(capture, tmp_path):
    """A clip of the 12 views at 4 fps, sampled back at 4 fps: sequential matching, poses recovered."""
    import imageio_ffmpeg

    photos, ref = capture
    from PIL import Image

    clip = tmp_path / "clip.mp4"
    writer = imageio_ffmpeg.write_frames(str(clip), (256, 256), fps=4, quality=10, macro_block_size=16)
    writer.send(None)
    for i in range(VIEWS):
        writer.send(np.asarray(Image.open(photos / f"r_{i}.png").convert("RGB")).tobytes())
    writer.close()
    out = tmp_path / "scene"
    summary = process(clip, out, fps=4, quiet=True)
    assert summary["kind"] == "video" and summary["matcher"] == "sequential"
    assert summary["images_given"] == VIEWS and summary["images_registered"] >= VIEWS - 1  # 12 measured
    scene = load_scene(out)
    originals = np.stack([np.asarray(Image.open(photos / f"r_{i}.png").convert("RGB"), np.float32) / 255
                          for i in range(VIEWS)])  # [V, H, W, 3]
    frames = [np.asarray(Image.open(out / n), np.float32)[:256, :256] / 255 for n in scene.names]
    order = [int(np.abs(originals[:, :f.shape[0], :f.shape[1]] - f).mean((1, 2, 3)).argmin()) for f in frames]
    assert len(set(order)) == len(order)  # each frame is a different view
    names = [n.split("/")[-1] for n in ref.names]
    e = errors_against(scene, ref, [names.index(f"r_{i}.png") for i in order])
    assert e["rotation_deg_median"] < 1.5 and e["centre_pct_median"] < 1.5, e


def test_exif_orientation_honoured(tmp_path):
    """A portrait photo stored landscape with EXIF orientation 6 is staged upright."""
    from PIL import Image

    v, u = np.mgrid[0:48, 0:32]
    upright = np.stack([u * 8, v * 5, 128 + 100 * np.sin(u / 5.0)], -1).astype(np.uint8)  # H=48, W=32: portrait
    src = tmp_path / "in"
    src.mkdir()
    for i in range(3):
        stored = Image.fromarray(np.rot90(upright, k=1).copy())  # orientation 6: turn 90 degrees clockwise to view
        exif = Image.Exif()
        exif[0x0112] = 6
        stored.save(src / f"p{i}.jpg", exif=exif, quality=95)
        upright = upright.copy()
        upright[0, 0] += 40  # not all identical
    staged = stage_images(src, tmp_path / "staged")
    assert staged.rotated == 3 and all(staged.sizes[n] == (32, 48) for n in staged.names)
    back = np.asarray(Image.open(tmp_path / "staged" / staged.names[-1]))
    assert np.abs(back.astype(int) - upright.astype(int)).mean() < 4  # JPEG noise only: the right way up
    assert np.abs(np.rot90(back, 2).astype(int) - upright.astype(int)).mean() > 20  # (upside down would fail)


def test_pairs_and_umeyama():
    assert len(image_pairs(6, False, 10)) == 15
    seq = image_pairs(30, True, 3)
    assert (0, 3) in seq and (0, 4) not in seq and (0, 6) in seq and (0, 12) in seq and (0, 24) in seq
    g = np.random.default_rng(0)
    src = g.normal(size=(10, 3))
    q, _ = np.linalg.qr(g.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    s, R2, t = umeyama(src, 2.5 * src @ R.T + [1, 2, 3])
    assert abs(s - 2.5) < 1e-9 and np.allclose(R2, R) and np.allclose(t, [1, 2, 3])


# ---------------------------------------------------------------------- bad input
def run_cli(capsys, *args):
    code = main(["process", *map(str, args), "--quiet"])
    err = capsys.readouterr().err.strip()
    return code, err


def assert_refused(capsys, tmp_path, source, *words, extra=()):
    out = tmp_path / "out_scene"
    code, err = run_cli(capsys, source, "--out", out, *extra)
    assert code == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err and "(fix: " in err, err
    for w in words:
        assert str(w) in err, err
    assert not out.exists() and not any(p.name.startswith(".out_scene") for p in tmp_path.iterdir())
    return err


def test_bad_missing_and_empty(capsys, tmp_path):
    assert_refused(capsys, tmp_path, tmp_path / "nope", "nope", "does not exist")
    (tmp_path / "empty").mkdir()
    assert_refused(capsys, tmp_path, tmp_path / "empty", "empty", "folder is empty")


def test_bad_no_images(capsys, tmp_path):
    d = tmp_path / "docs"
    d.mkdir()
    (d / "notes.txt").write_text("hello")
    assert_refused(capsys, tmp_path, d, "docs", "no images")


def test_bad_too_few(capsys, tmp_path, capture):
    photos, _ = capture
    d = tmp_path / "two"
    d.mkdir()
    for i in range(2):
        shutil.copyfile(photos / f"r_{i}.png", d / f"r_{i}.png")
    assert_refused(capsys, tmp_path, d, "two", "only 2 images", "at least 3")


def test_bad_unreadable_and_non_image(capsys, tmp_path, capture):
    photos, _ = capture
    d = tmp_path / "mixed"
    shutil.copytree(photos, d)
    (d / "broken.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    assert_refused(capsys, tmp_path, d, "broken.jpg", "cannot read image")
    (d / "broken.jpg").unlink()
    (d / "readme.md").write_text("# my photos")
    assert_refused(capsys, tmp_path, d, "readme.md", "not an image file")


def test_bad_video(capsys, tmp_path):
    clip = tmp_path / "clip.mp4"
    clip.write_bytes(b"\x00\x00\x00\x18ftypmp42 truncated garbage" * 10)
    assert_refused(capsys, tmp_path, clip, "clip.mp4", "cannot decode the video")


def test_bad_identical(capsys, tmp_path, capture):
    photos, _ = capture
    d = tmp_path / "same"
    d.mkdir()
    for i in range(4):
        shutil.copyfile(photos / "r_0.png", d / f"copy_{i}.png")
    assert_refused(capsys, tmp_path, d, "same", "all 4 images are identical")


def test_bad_too_few_registered(capsys, tmp_path, capture, views_with_noise):
    """6 real views + 8 noise images: the noise never registers; the message says how many and which."""
    photos, _ = capture
    d = views_with_noise(photos, 8)
    err = assert_refused(capsys, tmp_path, d, "noisy", "of 14 images registered", "noise_0.png")
    assert "need 7" in err


def test_bad_options(tmp_path, capture):
    photos, _ = capture
    with pytest.raises(InputError, match="camera-model"):
        process(photos, tmp_path / "o", SfmOptions(camera_model="FISHEYE"), quiet=True)
    (tmp_path / "exists").mkdir()
    with pytest.raises(InputError, match="already exists"):
        process(photos, tmp_path / "exists", quiet=True)


def test_align_poses_exact():
    """A similarity-moved copy of some poses aligns back exactly, and a pure rotation offset of one
    view shows up as that view's rotation error."""
    from omnirecon.cameras import look_at

    g = np.random.default_rng(1)
    eye = torch.from_numpy(g.normal(size=(8, 3)) * 0.3 + [0, 0, -4])  # a forward-facing cluster
    ref = look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0, -1.0, 0], dtype=torch.float64)).numpy()
    q, _ = np.linalg.qr(g.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    est = ref.copy()  # ref = s R est + t with s = 0.5, t = (3, -1, 2)
    est[:, :3, :3] = R.T @ ref[:, :3, :3]
    est[:, :3, 3] = (ref[:, :3, 3] - [3, -1, 2]) @ R / 0.5
    e = pose_errors(est, ref, extent=1.0)
    assert e["rotation_deg_max"] < 1e-4 and e["centre_pct_max"] < 1e-6
    c, s_ = np.cos(np.radians(2)), np.sin(np.radians(2))
    est[3, :3, :3] = est[3, :3, :3] @ np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]])
    e = pose_errors(est, ref, extent=1.0)
    assert 1.0 < e["rotation_deg"][3] < 2.0 and e["rotation_deg_median"] < 0.5


def test_per_image_cameras(capture, tmp_path):
    """One camera per photo: undistorted sizes differ, so every image is centre-cropped to one size."""
    photos, ref = capture
    out = tmp_path / "scene"
    summary = process(photos, out, SfmOptions(per_image_cameras=True), quiet=True)
    rec = pycolmap.Reconstruction(out / "sparse" / "0")
    assert rec.num_cameras() == VIEWS and len({(c.width, c.height) for c in rec.cameras.values()}) == 1
    assert summary["images_registered"] == VIEWS
    scene = load_scene(out)
    e = errors_against(scene, ref)
    assert e["rotation_deg_median"] < 2.0 and e["centre_pct_median"] < 2.0, e  # measured 0.96 deg, 0.68%


def test_stage_masks(capture, tmp_path):
    """Masks are matched by stem and written as COLMAP wants (<image name>.png, 0/255); a missing one is named."""
    from PIL import Image

    from omnirecon.capture.images import stage_masks

    photos, _ = capture
    staged = stage_images(photos, tmp_path / "staged")
    masks = tmp_path / "masks"
    masks.mkdir()
    for n in staged.names[:-1]:
        a = np.zeros((256, 256), np.uint8)
        a[64:192, 64:192] = 7
        Image.fromarray(a).save(masks / n)
    with pytest.raises(InputError, match=f"no mask for {staged.names[-1]}"):
        stage_masks(masks, staged, tmp_path / "m")
    Image.fromarray(np.full((256, 256), 255, np.uint8)).save(masks / staged.names[-1])
    out = stage_masks(masks, staged, tmp_path / "m")
    m = np.asarray(Image.open(out / f"{staged.names[0]}.png"))
    assert set(np.unique(m)) == {0, 255} and m[128, 128] == 255 and m[0, 0] == 0


def test_bench_poses_tiny_and_section(tmp_path):
    """`python -m bench poses --tiny` measures one procedural scene; the page renders its "Pose recovery" table."""
    import json

    from bench import poses
    from bench.report import poses as poses_section

    poses.main(["--tiny", "--out", str(tmp_path / "poses.json")])
    r = json.loads((tmp_path / "poses.json").read_text())
    row = r["scenes"][0]
    assert row["registered"] == VIEWS and row["rotation_deg_median"] < 1.0 and "commit" in r["provenance"]
    text = poses_section.section(tmp_path)
    assert "## Pose recovery" in text and f"| {VIEWS} / {VIEWS} (100%) |" in text and "Provenance: commit" in text


@pytest.mark.slow
def test_reconstruct_writes_report(capture, tmp_path, run_cli):
    """`omnirecon reconstruct PHOTOS`: process, mesh, finetune, export and a report whose pictures exist
    (small: 48-pixel images, 2 s of fine-tuning; the numbers are not the point here)."""
    import json
    import re
    from pathlib import Path

    photos, _ = capture
    ckpt = Path(__file__).resolve().parents[2] / "checkpoints" / "omnirecon-tiny"
    out = tmp_path / "rec"
    code, _, err = run_cli(["reconstruct", photos, "--out", out, "--ckpt", ckpt, "--resolution", "48", "--mesh-resolution", "48",
                            "--finetune-seconds", "2", "--frames", "4", "--no-viewer", "--threads", "1"])
    assert code == 0, err
    page = (out / "index.html").read_text()
    pictures = re.findall(r'src="([^"]+)"', page)
    assert {"cameras.png", "mesh_preview.png", "finetune/curve.png", "finetune/before_after.png",
            "path.mp4"} <= set(pictures)
    assert all((out / p).is_file() and (out / p).stat().st_size > 1000 for p in pictures)
    assert "<th>coverage</th>" in page  # PSNR beside coverage, in the table and in the summary line
    assert re.search(r"PSNR [\d.]+ dB before, [\d.]+ dB after [\d.]+ s of fine-tuning \(coverage \d+%\)", page)
    record = json.loads((out / "reconstruct.json").read_text())
    assert record["process"]["images_registered"] == VIEWS and (out / "scene" / "sparse" / "0").is_dir()
    assert (out / "export" / "mesh.glb").is_file() and (out / "finetune" / "checkpoint").is_dir()
    scored = json.loads((out / "finetune" / "curve.json").read_text())["render"]  # the export starts as finetune scored
    setting = json.loads((out / "export" / "export.json").read_text())["setting"]
    assert {k: setting[k] for k in scored} == scored and setting["blend"] in ("network", "angle")
    # Every record names files inside the output relative to --out, never the temporary build folder.
    for f in out.rglob("*.json"):
        text = f.read_text()
        assert ".tmp" not in text and str(tmp_path) not in text, (f, re.findall(r'"[^"]*\.tmp[^"]*"', text))
    assert record["scene"] == "scene" and all((out / p).exists() for p in record["export"])
    assert set(record["cpu_seconds"]) == set(record["seconds"]) - {"total"} and record["threads"] == 1
    reach = record["path"]["nearest_photo_degrees"]  # how far the video's frames are from the photos
    assert 0 <= reach["median"] <= reach["max"] <= 180 and "from the nearest photo" in page
    assert json.loads((out / "finetune" / "checkpoint" / "meta.json").read_text())["extra"]["finetuned_on"] == "scene"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no lock, no temporary


def test_undistort_mask_follows_the_camera():
    """A mask drawn through a distorted camera (object where the ray's x / z > 0.1, a curved edge in the photo)
    comes out of the undistortion as the pinhole camera's straight column of x / z = 0.1 (u = 138)."""
    from omnirecon.capture.masks import undistort_mask

    d = pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 200.0, 256, 192)
    d.params = [200.0, 128.0, 96.0, -0.2]
    p = pycolmap.Camera.create_from_model_name(2, "PINHOLE", 220.0, 240, 180)
    p.params = [220.0, 220.0, 120.0, 90.0]
    xs, ys = np.meshgrid(np.arange(256) + 0.5, np.arange(192) + 0.5)
    rays = d.cam_from_img(np.stack([xs.ravel(), ys.ravel()], 1)).reshape(192, 256, 2)
    out = undistort_mask(rays[..., 0] > 0.1, d, p)
    first = out.argmax(1)  # [180] the first object column of each row
    assert out.shape == (180, 240) and out[:, -1].all() and (np.abs(first - 142) <= 1).all(), (first.min(), first.max())


def test_process_keeps_the_masks(capture, tmp_path):
    """--masks: the scene carries the object masks, undistorted and cropped like its photos (one camera per photo,
    every image cropped to one size) in masks/ and masks_2/, masks_4/, which the reader gives as Scene.masks. The
    masks here are the photos' own bright pixels, so each must agree with its undistorted photo thresholded alike:
    measured at least 0.979 of the pixels at full size (0.974 at half); the masks shifted by 2 px: at most 0.970."""
    from pathlib import Path

    from PIL import Image

    from omnirecon.capture.process import summary_lines

    photos, _ = capture
    masks = tmp_path / "masks"
    masks.mkdir()
    cut = {}
    for p in sorted(photos.iterdir()):
        lum = np.asarray(Image.open(p).convert("L"), np.float32)
        cut[p.name] = float(np.median(lum))
        Image.fromarray(np.where(lum > cut[p.name], 255, 0).astype(np.uint8)).save(masks / p.name)
    out = tmp_path / "scene"
    summary = process(photos, out, SfmOptions(per_image_cameras=True, mask_dilate=8), quiet=True, masks=masks)
    assert summary["images_registered"] == VIEWS and len(list((out / "masks_4").iterdir())) == VIEWS
    assert any(x.startswith("object masks kept") for x in summary_lines(summary))
    for ds in (1, 2):
        scene = load_scene(out, options=ReadOptions(downscale=ds))
        assert scene.masks is not None and scene.masks.shape == (VIEWS, scene.height, scene.width)
        for i, name in enumerate(scene.names):
            lum = scene.images[i].numpy() @ np.array([0.299, 0.587, 0.114]) * 255  # [H, W]
            bright = lum > cut[Path(name).name]
            inner = (slice(2, -2), slice(2, -2))  # the undistorted border samples outside the photo
            agree = float((bright[inner] == scene.masks[i].numpy()[inner]).mean())
            assert agree > (0.975 if ds == 1 else 0.96), (ds, name, agree)


def test_object_masks_decide_reconstruct_meshing(processed, tmp_path):
    """`reconstruct` meshes with the object masks (`mesh --masks`) on object captures that have them: a procedural
    object scene (masks) yes, a forward-facing one (masks) and photos processed without --masks (none) no."""
    from omnirecon.engine.scenes import object_masks

    out, _ = processed
    assert not object_masks(out)
    assert object_masks(generate_scene(tmp_path / "o", 1, SynthOptions(rig="object", views=4, resolution=32)))
    assert not object_masks(generate_scene(tmp_path / "f", 1, SynthOptions(rig="forward", views=4, resolution=32)))
