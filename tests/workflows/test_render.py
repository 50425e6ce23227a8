"""Camera paths (orbit, spiral, interp) and ``omnirecon render`` end to end with the floor."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import ROOT

from omnirecon import trajectory
from omnirecon.cameras import Cameras, look_at
from omnirecon.cli import main
from omnirecon.data.io import read_image
from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.engine.scenes import load_at_resolution
from omnirecon.workflows.render import _write_gif


def assert_rigid(c2w: torch.Tensor) -> None:
    R = c2w[:, :3, :3]
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    assert torch.allclose(R.transpose(1, 2) @ R, eye, atol=1e-9)
    assert torch.allclose(torch.linalg.det(R), torch.ones(len(R), dtype=R.dtype), atol=1e-9)
    assert torch.allclose(c2w[:, 3], torch.tensor([0, 0, 0, 1.0], dtype=c2w.dtype).expand(len(c2w), 4))


def hemisphere_cameras(n=12, radius=3.0) -> Cameras:
    """Cameras on a ring at 30 degrees elevation around the origin, z up, looking at it."""
    a = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    el = math.radians(30)
    eye = radius * torch.stack([math.cos(el) * torch.cos(a), math.cos(el) * torch.sin(a),
                                torch.full_like(a, math.sin(el))], -1)
    c2w = look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0, 0, 1.0], dtype=torch.float64))
    return Cameras(torch.full((n,), 20.0), torch.full((n,), 20.0), 8.0, 8.0, c2w, 16, 16)


def test_orbit_circles_at_mean_distance_and_elevation():
    cams = hemisphere_cameras()
    c2w = trajectory.orbit(cams, 10)
    assert c2w.shape == (10, 4, 4)
    assert_rigid(c2w)
    c = c2w[:, :3, 3]
    assert torch.allclose(c.norm(dim=-1), torch.full((10,), 3.0, dtype=torch.float64), atol=1e-6)
    assert torch.allclose(c[:, 2], torch.full((10,), 1.5, dtype=torch.float64), atol=1e-6)  # 3 sin 30°
    assert torch.allclose(c[0], cams.centers[0], atol=1e-6)  # starts at camera 0
    fwd = torch.nn.functional.normalize(-c, dim=-1)
    assert torch.allclose(c2w[:, :3, 2], fwd, atol=1e-6)  # looks at the centre
    assert (c2w[:, 2, 1] < 0).all()  # image "down" (+y) points down in the world: upright
    half = trajectory.orbit(cams, 5, arc_degrees=90)
    assert torch.allclose(half[-1, :3, 3], cams.centers[3], atol=1e-6)  # a partial arc includes its end



def test_orbit_sweeps_only_the_arc_the_photos_cover():
    """arc_degrees=None: cameras on a 90-degree arc (a wall-mounted object) give a path that stays on that arc,
    there and back, never behind the object; cameras all around give the full orbit unchanged."""
    ring = hemisphere_cameras(n=24)
    part = ring[list(range(7))]  # azimuths 0..90 degrees
    c2w = trajectory.orbit(part, 16, torch.zeros(3, dtype=torch.float64), None)
    assert_rigid(c2w)
    az = torch.rad2deg(torch.atan2(c2w[:, 1, 3], c2w[:, 0, 3]))  # the mean up tilts a little toward the arc
    assert az.min() > -2.0 and az.max() < 92.0 and az.max() > 88.0  # spans the arc, never leaves it
    assert abs(float(az[0])) < 2.0 and abs(float(az[8]) - 90) < 2.0  # one end, then the other ...
    assert torch.allclose(c2w[1, :3, 3], c2w[15, :3, 3], atol=1e-6)  # ... and back: the video loops
    away = trajectory.nearest_photo_degrees(c2w, part, torch.zeros(3, dtype=torch.float64))
    assert away.max() < 7.6  # within half the 15-degree spacing
    full = trajectory.nearest_photo_degrees(trajectory.orbit(part, 16, torch.zeros(3, dtype=torch.float64)), part,
                                            torch.zeros(3, dtype=torch.float64))
    assert full.max() > 90  # the full orbit goes behind
    assert torch.allclose(trajectory.orbit(ring, 10, None, None), trajectory.orbit(ring, 10))

def test_spiral_around_mean_pose():
    # Forward-facing grid: parallel cameras looking along +z.
    xy = torch.stack(torch.meshgrid(torch.linspace(-1, 1, 3), torch.linspace(-0.5, 0.5, 3), indexing="ij"), -1)
    eye = torch.cat([xy.reshape(-1, 2), torch.zeros(9, 1)], -1).double()
    c2w = look_at(eye, eye + torch.tensor([0, 0, 1.0], dtype=torch.float64), torch.tensor([0, -1.0, 0]).double())
    cams = Cameras(torch.full((9,), 20.0), torch.full((9,), 20.0), 8.0, 8.0, c2w, 16, 16)
    path = trajectory.spiral(cams, near=2.0, far=10.0, frames=12)
    assert path.shape == (12, 4, 4)
    assert_rigid(path)
    c = path[:, :3, 3]
    assert c[:, 0].abs().max() <= 1.0 + 1e-9 and c[:, 1].abs().max() <= 0.5 + 1e-9
    assert (path[:, 2, 2] > 0.9).all()  # still facing forward
    assert (path[:, 1, 1] > 0.9).all()  # and upright (+y down, as the inputs)


def test_quaternion_round_trip_and_slerp():
    g = torch.Generator().manual_seed(0)
    q = torch.nn.functional.normalize(torch.randn(64, 4, generator=g, dtype=torch.float64), dim=-1)
    R = trajectory.quaternion_to_matrix(q)
    R = torch.cat([R, torch.diag(torch.tensor([1.0, -1, -1], dtype=torch.float64))[None]])  # a 180° turn
    back = trajectory.quaternion_to_matrix(trajectory.matrix_to_quaternion(R))
    assert torch.allclose(back, R, atol=1e-9)
    q0 = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)
    q1 = torch.tensor([math.cos(0.5), 0, 0, math.sin(0.5)], dtype=torch.float64)  # 1 rad about z
    mid = trajectory.quaternion_to_matrix(trajectory.slerp(q0, q1, torch.tensor(0.5, dtype=torch.float64)))
    assert torch.atan2(mid[1, 0], mid[0, 0]).item() == pytest.approx(0.5, abs=1e-9)


def test_interp_passes_through_keyframes():
    keys = hemisphere_cameras(5)
    frames = 3 * (len(keys) - 1) + 1
    cams = trajectory.interpolate(keys, frames)
    assert len(cams) == frames
    assert_rigid(cams.c2w)
    for j in range(len(keys)):
        assert torch.allclose(cams.c2w[3 * j], keys.c2w[j], atol=1e-9)
    # in between: centres on the chord, rotations between the neighbours
    assert torch.allclose(cams.centers[1], keys.centers[0] * 2 / 3 + keys.centers[1] / 3, atol=1e-9)


def test_camera_path_kinds_from_cameras():
    """trajectory.camera_path: cameras and a kind give the path of that kind (the same poses as the
    primitives, camera 0's intrinsics); a bad kind, a spiral without depths or bad keyframes: ValueError."""
    cams = hemisphere_cameras(10)
    orbit = trajectory.camera_path(cams, "orbit", 6, arc=180.0)
    assert torch.equal(orbit.c2w, trajectory.orbit(cams, 6, None, 180.0)) and (orbit.width, orbit.height) == (16, 16)
    spiral = trajectory.camera_path(cams, "spiral", 5, near=1.0, far=5.0, rots=1.0)
    assert torch.equal(spiral.c2w, trajectory.spiral(cams, 1.0, 5.0, 5, 1.0))
    interp = trajectory.camera_path(cams, "interp", 9)
    keys = trajectory.default_keyframes(len(cams))
    assert len(keys) == trajectory.MAX_DEFAULT_KEYFRAMES
    assert torch.equal(interp.c2w, trajectory.interpolate(cams[keys], 9).c2w)
    for kw in ({"kind": "spiral"}, {"kind": "interp", "keyframes": [3]}, {"kind": "interp", "keyframes": [0, 99]},
               {"kind": "zoom"}):
        with pytest.raises(ValueError):
            trajectory.camera_path(cams, frames=4, **kw)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return generate_scene(tmp_path_factory.mktemp("synth"), 900_321, SynthOptions(resolution=32, views=12))


@pytest.mark.parametrize("path, extra, frames", [
    ("orbit", [], 4),
    ("spiral", [], 4),
    ("interp", ["--keyframes", "0", "5", "11"], 5),  # frame times 0, .5, 1, 1.5, 2: frames 0, 2, 4 are keyframes
])
def test_render_cli(path, extra, frames, scene, tmp_path, capsys):
    out = tmp_path / path
    code = main(["render", "--model", "floor", "--scene", str(scene), "--path", path, "--frames", str(frames),
                 "--num-views", "3", "--resolution", "24", "--out", str(out), *extra])
    assert code == 0, capsys.readouterr().err
    assert len(list((out / "frames").glob("*.png"))) == frames
    video = [p for p in out.iterdir() if p.name in ("video.mp4", "video.gif")]
    assert len(video) == 1 and video[0].stat().st_size > 0
    meta = json.loads((out / "cameras.json").read_text())
    assert len(meta["frames"]) == frames and meta["width"] == 24
    assert all(len(f["sources"]) == 3 for f in meta["frames"])
    c2w = torch.tensor([f["c2w"] for f in meta["frames"]], dtype=torch.float64)
    assert_rigid(c2w)
    if path == "interp":
        keys = load_at_resolution(scene, 24).cameras.c2w[[0, 5, 11]]
        assert torch.allclose(c2w[[0, 2, 4]], keys, atol=1e-9)
        assert meta["frames"][0]["sources"][0] == 0  # a keyframe's nearest source is its own view


@pytest.mark.parametrize("preset, levers", [("gpnr-tiny", ["--samples", "8", "--precision", "fp32"]),
                                            ("omnirecon-tiny", ["--render-pass", "fine"])])
def test_render_levers_change_the_frame_a_little_and_are_recorded(preset, levers, scene, tmp_path, capsys):
    ckpt = ROOT / "checkpoints" / preset
    if not (ckpt / "model.safetensors").is_file():
        pytest.skip(f"the shipped {preset} checkpoint is not in this clone")

    def run(name: str, extra: list[str]):
        out = tmp_path / name
        code = main(["render", "--ckpt", str(ckpt), "--scene", str(scene), "--frames", "1", "--num-views", "3",
                     "--resolution", "24", "--no-video", "--threads", "1", "--out", str(out), *extra])
        assert code == 0, capsys.readouterr().err
        return read_image(out / "frames" / "0000.png").astype(np.float64), json.loads((out / "cameras.json").read_text())

    full, _ = run("full", [])
    fast, meta = run("fast", levers)
    assert not np.array_equal(full, fast)  # the levers change what is rendered ...
    assert np.abs(full - fast).mean() < 0.1  # ... but not into another picture
    options = dict(meta["model"]["render_options"])
    assert options.pop("guided")["on"] is False  # surface-guided sampling stays off unless asked for
    assert options == {"render_pass": "fine" if "fine" in levers else "auto",
                       "precision": "fp32" if "fp32" in levers else "auto"}
    assert meta["model"].get("render_samples") == ({"render_samples": 8} if "--samples" in levers else None)


def test_gif_fallback(tmp_path):
    frames = [np.full((5, 7, 3), i * 40, np.uint8) for i in range(3)]
    path = _write_gif(tmp_path / "video.gif", frames, fps=10)
    from PIL import Image

    with Image.open(path) as im:
        assert im.n_frames == 3 and im.size == (7, 5)


@pytest.mark.parametrize("args, message", [
    (["--frames", "0"], "--frames"),
    (["--path", "interp", "--keyframes", "0", "99"], "--keyframes"),
    (["--num-views", "99"], "--num-views"),
    (["--samples", "1"], "--samples"),
])
def test_render_bad_input_exit_2(args, message, scene, tmp_path, capsys):
    code = main(["render", "--model", "floor", "--scene", str(scene), "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0]
