import json
import math

import pytest
import torch

from omnirecon.cameras import Cameras, look_at
from omnirecon.workflows.inspect import _line_distance, fundamental

# (scene, reader, downscale): every real scene, at a reduced size to keep the suite fast
SHARED = [
    ("blender/lego", "blender", 4), ("blender/chair", "blender", 4), ("instant_ngp/fox", "ngp", 1),
    ("llff/fern", "llff", 1), ("llff/ethiopianHead", "llff", 2), ("neus_dtu/dtu_scan24", "dtu_neus", 2),
    ("neus_dtu/dtu_scan37", "dtu_neus", 2),
]


def test_fundamental_matrix_maps_points_to_their_epipolar_lines():
    ang = torch.tensor([0.0, 0.4], dtype=torch.float64)
    eye = torch.stack([3 * torch.sin(ang), -3 * torch.cos(ang), 0.5 + 0 * ang], -1)
    c2w = look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0, 0, 1.0], dtype=torch.float64))
    cams = Cameras(torch.tensor([50.0, 60]), torch.tensor([52.0, 58]), torch.tensor([31.0, 33]),
                   torch.tensor([25.0, 23]), c2w, 64, 48).to(dtype=torch.float64)
    pts = torch.randn(20, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.5
    uv = cams.project(pts).uv
    F = fundamental(cams, 0, 1)
    assert _line_distance(F, uv[0], uv[1]).max() < 1e-9
    # a point moved off its line by 2 px along the line's normal is 2 px away
    h = torch.cat([uv[0], torch.ones(20, 1, dtype=torch.float64)], 1)
    line = h @ F.T
    normal = line[:, :2] / line[:, :2].norm(dim=1, keepdim=True)
    d = _line_distance(F, uv[0], uv[1] + 2 * normal)
    assert torch.allclose(d[0] * 0 + 2, d, atol=0.5)  # symmetric distance: ~2 px when views are similar


def run_inspect(args, tmp_path):
    """``omnirecon inspect ARGS --out <tmp>/inspect`` through the CLI's entry point, in this process (an interpreter
    start per scene cost more than inspecting it); its summary.json."""
    from omnirecon.cli import main

    out = tmp_path / "inspect"
    assert main(["inspect", *map(str, args), "--out", str(out)]) == 0  # the error is on stderr (shown on failure)
    for name in ("cameras.png", "epipolar.png"):
        assert (out / name).stat().st_size > 10_000  # a real picture, not an empty canvas
    return json.loads((out / "summary.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("rel,fmt,downscale", SHARED, ids=[s[0] for s in SHARED])
def test_inspect_real_scenes(rel, fmt, downscale, shared_data, tmp_path):
    path = shared_data(rel)
    s = run_inspect([path, "--downscale", downscale, "--max-views", 30], tmp_path)
    assert s["format"] == fmt
    c = s["consistency"]
    # poses agree with the images: matched features lie on their epipolar lines (pixels at this size)
    assert c["epipolar_px"] is not None and c["epipolar_px"] < 2.0, c
    if "hull_fraction" in c:
        assert c["hull_fraction"] > 0.95, c


def test_scores_detect_broken_poses(shared_data):
    """Small pose errors raise the epipolar score; a yaw that shifts silhouettes lowers the hull score."""
    from dataclasses import replace

    from omnirecon.data import ReadOptions, load_scene
    from omnirecon.workflows.inspect import epipolar_score, neighbour_pairs, visual_hull_score

    scene = load_scene(shared_data("neus_dtu/dtu_scan24"), options=ReadOptions(downscale=2, max_views=12))
    pairs = neighbour_pairs(scene, 4)
    good_epi, _ = epipolar_score(scene, pairs)
    good_hull = visual_hull_score(scene, torch.Generator().manual_seed(0))

    def rotated(axis: int, degrees: float):
        a = math.radians(degrees)
        c, s = math.cos(a), math.sin(a)
        i, j = [k for k in range(3) if k != axis]
        rot = torch.eye(3, dtype=scene.cameras.c2w.dtype)
        rot[i, i], rot[i, j], rot[j, i], rot[j, j] = c, -s, s, c
        c2w = scene.cameras.c2w.clone()
        c2w[1::2, :3, :3] = c2w[1::2, :3, :3] @ rot  # every other camera
        return replace(scene, cameras=replace(scene.cameras, c2w=c2w))

    bad_epi, _ = epipolar_score(rotated(2, 3.0), pairs)  # 3 degree roll about the optical axis
    bad_hull = visual_hull_score(rotated(1, 8.0), torch.Generator().manual_seed(0))  # 8 degree yaw
    assert good_epi < 1.0 and bad_epi > 3 * good_epi, (good_epi, bad_epi)
    assert good_hull > 0.98 and bad_hull < good_hull - 0.05, (good_hull, bad_hull)


@pytest.mark.parametrize("args", [["--downscale", "0"], ["--pair", "0", "0"], ["--no-such-flag"], ["--format", "nerf"]])
def test_inspect_bad_flags_exit_2(args, tmp_path, shared_data, run_cli):
    path = shared_data("llff/fern")
    code, _, err = run_cli(["inspect", path, *args, "--out", tmp_path])  # the CLI's entry point, in this process
    assert code == 2, (code, err[-500:])
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1  # one line naming the flag
    assert not list(tmp_path.glob("*.png"))  # nothing half-written
