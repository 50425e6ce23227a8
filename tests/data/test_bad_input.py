"""Bad input: every case raises InputError naming the file, and the CLI exits with code 2 and one
line on stderr, without a traceback (``--verbose`` shows it).

Fixtures are tiny synthetic scenes (8x8 images) built in ``tmp_path``.
"""

import json
import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from omnirecon.cameras import look_at
from omnirecon.data import load_scene
from omnirecon.data.colmap_io import Camera, Image, Model, Points, rotmat_to_qvec, write_model
from omnirecon.data.io import write_image
from omnirecon.errors import InputError

N = 3


def ring_c2w(n=N):
    """OpenCV camera-to-world matrices on a ring around the origin. ``# [n, 4, 4]``"""
    a = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    eye = torch.stack([4 * torch.cos(a), 4 * torch.sin(a), torch.full_like(a, 1.0)], -1)
    return look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0, 0, 1.0], dtype=torch.float64))


def ring_gl(n=N):
    """The same poses in the OpenGL camera frame (Blender / instant-ngp json). ``# [n, 4, 4]``"""
    return ring_c2w(n) @ torch.diag(torch.tensor([1.0, -1, -1, 1], dtype=torch.float64))


def tiny_image(path, w=8, h=8, seed=0):
    write_image(path, np.random.default_rng(seed).uniform(size=(h, w, 3)))


def blender_scene(root, mats=None, sizes=None):
    """``transforms_train.json`` + ``train/r_i.png``; ``mats`` replaces the OpenGL matrices."""
    gl = ring_gl().tolist()
    mats = gl if mats is None else mats
    for i in range(len(mats)):
        tiny_image(root / "train" / f"r_{i}.png", *(sizes[i] if sizes else (8, 8)), seed=i)
    frames = [{"file_path": f"./train/r_{i}", "transform_matrix": m} for i, m in enumerate(mats)]
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    return root


def llff_scene(root, rows=N, images=N, cols=17):
    c2w = ring_c2w(rows).numpy()
    llff = np.stack([c2w[:, :3, 1], c2w[:, :3, 0], -c2w[:, :3, 2], c2w[:, :3, 3]], -1)  # [down, right, back, t]
    hwf = np.tile([[8.0], [8.0], [10.0]], (rows, 1, 1))
    arr = np.concatenate([np.concatenate([llff, hwf], -1).reshape(rows, 15), np.tile([[1.0, 9.0]], (rows, 1))], 1)
    root.mkdir(parents=True, exist_ok=True)
    np.save(root / "poses_bounds.npy", arr[:, :cols])
    for i in range(images):
        tiny_image(root / "images" / f"img_{i:03d}.png", seed=i)
    return root


def colmap_scene(root, model="PINHOLE", params=(10.0, 10.0, 4.0, 4.0), ext=".txt"):
    w2c = torch.linalg.inv(ring_c2w()).numpy()
    pts = np.random.default_rng(0).uniform(-0.5, 0.5, (20, 3))
    images = [Image(i + 1, rotmat_to_qvec(w2c[i, :3, :3]), w2c[i, :3, 3], 1, f"im{i}.png") for i in range(N)]
    for i in range(N):
        tiny_image(root / "images" / f"im{i}.png", seed=i)
    write_model(Model({1: Camera(1, model, 8, 8, np.array(params))}, images,
                      Points(np.arange(20), pts, np.zeros((20, 3), np.uint8), np.zeros(20),
                             [np.zeros((0, 2), np.int64)] * 20), None, None), root / "sparse" / "0", ext)
    return root


def assert_bad_input(scene_path, named, run_cli, match=None):
    """``load_scene`` raises InputError naming ``named``; the CLI exits 2 with one line naming it."""
    with pytest.raises(InputError) as info:
        load_scene(scene_path)
    msg = str(info.value)
    assert str(named) in msg and "\n" not in msg, msg
    if match:
        assert match in msg, msg
    rc, _, err = run_cli(["inspect", scene_path, "--out", scene_path.parent / "inspect_out"])
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1, err
    assert lines[0].startswith("omnirecon: error: ") and str(named) in lines[0] and "Traceback" not in err


# ---------------------------------------------------------------------- files and folders
def test_path_does_not_exist(tmp_path, run_cli):
    assert_bad_input(tmp_path / "nope", tmp_path / "nope", run_cli, "does not exist")


def test_empty_folder(tmp_path, run_cli):
    (tmp_path / "empty").mkdir()
    assert_bad_input(tmp_path / "empty", tmp_path / "empty", run_cli, "no supported scene format")


def test_missing_image(tmp_path, run_cli):
    root = blender_scene(tmp_path / "s")
    (root / "train" / "r_1.png").unlink()
    assert_bad_input(root, root / "train" / "r_1.png", run_cli, "missing")


def test_corrupt_image(tmp_path, run_cli):
    root = blender_scene(tmp_path / "s")
    (root / "train" / "r_2.png").write_bytes(b"this is not a png" * 10)
    assert_bad_input(root, root / "train" / "r_2.png", run_cli, "cannot read image")


def test_truncated_image(tmp_path, run_cli):
    root = blender_scene(tmp_path / "s", sizes=[(64, 64)] * N)
    data = (root / "train" / "r_0.png").read_bytes()
    (root / "train" / "r_0.png").write_bytes(data[: len(data) // 2])
    assert_bad_input(root, root / "train" / "r_0.png", run_cli, "cannot read image")


def test_mismatched_image_sizes(tmp_path, run_cli):
    root = blender_scene(tmp_path / "s", sizes=[(8, 8), (8, 8), (10, 8)])
    assert_bad_input(root, root / "train" / "r_2.png", run_cli, "10x8")


def test_invalid_json(tmp_path, run_cli):
    root = blender_scene(tmp_path / "s")
    (root / "transforms_train.json").write_text('{"camera_angle_x": 0.7, "frames": [')
    assert_bad_input(root, root / "transforms_train.json", run_cli, "invalid JSON")


# ---------------------------------------------------------------------- matrices and poses
def test_wrong_matrix_shape_blender(tmp_path, run_cli):
    mats = ring_gl().tolist()
    mats[1] = [row[:3] for row in mats[1][:3]]  # 3x3
    root = blender_scene(tmp_path / "s", mats=mats)
    assert_bad_input(root, root / "transforms_train.json", run_cli, "shape 3x3")


def test_wrong_matrix_shape_llff(tmp_path, run_cli):
    root = llff_scene(tmp_path / "s", cols=16)
    assert_bad_input(root, root / "poses_bounds.npy", run_cli, "N x 17")


def test_non_finite_pose(tmp_path, run_cli):
    mats = ring_gl().tolist()
    mats[2][0][3] = float("nan")
    root = blender_scene(tmp_path / "s", mats=mats)
    assert_bad_input(root, root / "transforms_train.json", run_cli, "NaN")


@pytest.mark.parametrize("kind", ["scaled", "reflection"])
def test_non_rigid_pose(tmp_path, run_cli, kind):
    gl = ring_gl()
    gl[1, :3, :3] *= 2.0 if kind == "scaled" else torch.tensor([-1.0, 1, 1], dtype=torch.float64)
    root = blender_scene(tmp_path / "s", mats=gl.tolist())
    assert_bad_input(root, root / "transforms_train.json", run_cli, "not rigid")


def test_non_rigid_pose_llff(tmp_path, run_cli):
    root = llff_scene(tmp_path / "s")
    arr = np.load(root / "poses_bounds.npy")
    arr[0, [0, 5, 10]] *= -1  # flip one rotation column: a reflection
    np.save(root / "poses_bounds.npy", arr)
    assert_bad_input(root, root / "poses_bounds.npy", run_cli, "reflection")


# ---------------------------------------------------------------------- counts and keys
def test_llff_row_image_count_mismatch(tmp_path, run_cli):
    root = llff_scene(tmp_path / "s", rows=N, images=N + 1)
    assert_bad_input(root, root / "images", run_cli, "3 poses")


def test_missing_npz_keys(tmp_path, run_cli):
    root = tmp_path / "s"
    for i in range(N):
        tiny_image(root / "image" / f"{i:06d}.png", seed=i)
    P = np.eye(4)
    P[:3, :3] = [[10, 0, 4], [0, 10, 4], [0, 0, 1]]
    P[2, 3] = 3
    np.savez(root / "cameras_sphere.npz", **{f"world_mat_{i}": P for i in range(N)},
             **{f"scale_mat_{i}": np.eye(4) for i in range(N - 1)})
    assert_bad_input(root, root / "cameras_sphere.npz", run_cli, f"scale_mat_{N - 1}")


def test_malformed_mvsnet_cam(tmp_path, run_cli):
    root = tmp_path / "s"
    for i in range(N):
        tiny_image(root / "images" / f"{i:08d}.png", seed=i)
        (root / "cams").mkdir(parents=True, exist_ok=True)
        (root / "cams" / f"{i:08d}_cam.txt").write_text("extrinsic\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n\nintrinsic\n"
                                                        "10 0 4\n0 10 4\n0 0 1\n\n1 0.1\n")
    (root / "cams" / "00000001_cam.txt").write_text("extrinsic\n1 0 0\n")
    assert_bad_input(root, root / "cams" / "00000001_cam.txt", run_cli, "malformed cam file")


# ---------------------------------------------------------------------- camera models
@pytest.mark.parametrize("model,params", [
    ("FULL_OPENCV", (10.0, 10.0, 4.0, 4.0, 0.1, 0, 0, 0, 0, 0, 0, 0)),
    ("OPENCV_FISHEYE", (10.0, 10.0, 4.0, 4.0, 0.1, 0, 0, 0)),
])
@pytest.mark.parametrize("ext", [".txt", ".bin"])
def test_unsupported_colmap_model(tmp_path, run_cli, model, params, ext):
    root = colmap_scene(tmp_path / "s", model, params, ext)
    assert_bad_input(root, root / "sparse" / "0" / f"cameras{ext}", run_cli, model)


def test_truncated_colmap_binary(tmp_path, run_cli):
    root = colmap_scene(tmp_path / "s", ext=".bin")
    f = root / "sparse" / "0" / "images.bin"
    f.write_bytes(f.read_bytes()[:50])
    assert_bad_input(root, f, run_cli, "malformed COLMAP file")


def test_unsupported_ngp_model(tmp_path, run_cli):
    root = tmp_path / "s"
    gl = ring_gl().tolist()
    for i in range(N):
        tiny_image(root / "images" / f"{i}.png", seed=i)
    meta = {"camera_model": "OPENCV_FISHEYE", "fl_x": 10, "fl_y": 10, "cx": 4, "cy": 4, "w": 8, "h": 8,
            "k1": 0.1, "frames": [{"file_path": f"images/{i}.png", "transform_matrix": m} for i, m in enumerate(gl)]}
    (root / "transforms.json").write_text(json.dumps(meta))
    assert_bad_input(root, root / "transforms.json", run_cli, "OPENCV_FISHEYE")


# ---------------------------------------------------------------------- the real process
def _subprocess(args):
    return subprocess.run([sys.executable, "-m", "omnirecon.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def test_cli_process_exit_code_and_one_line(tmp_path):
    root = blender_scene(tmp_path / "s")
    (root / "train" / "r_1.png").unlink()
    proc = _subprocess(["inspect", root, "--out", tmp_path / "out"])
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()] and str(root / "train" / "r_1.png") in proc.stderr


def test_verbose_shows_traceback(tmp_path):
    proc = _subprocess(["inspect", tmp_path / "nope", "--verbose"])
    assert proc.returncode != 0 and "Traceback" in proc.stderr and "InputError" in proc.stderr
