"""TSDF fusion, marching cubes, cleaning, export in the input frame, and ``omnirecon mesh`` end to end."""

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from omnirecon.cameras import Cameras, look_at
from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.engine.checkpoint import save_checkpoint
from omnirecon.engine.scenes import load_at_resolution
from omnirecon.mesh import geometry
from omnirecon.mesh.build import MeshOptions
from omnirecon.mesh.clean import clean_mesh, dilate_masks
from omnirecon.mesh.depth import shifted_cameras
from omnirecon.mesh.files import to_input_frame, write_mesh
from omnirecon.mesh.fusion import extract_mesh, fuse
from omnirecon.models.registry import build_model

TINY_IBRNET = {"coarse_samples": 8, "fine_samples": 4, "channels": [8, 8, 16], "feature_dim": 8}


@pytest.fixture(scope="module")
def synth_scene(tmp_path_factory) -> Path:
    """A 40 x 40 procedural scene of 16 views, loaded as 12 train views (0-11), val 12-13, test 14-15."""
    return generate_scene(tmp_path_factory.mktemp("synth"), 900_123, SynthOptions(resolution=40, views=16))


def ring_cameras(n: int = 8, res: int = 64, f: float = 80.0, radius: float = 3.0) -> Cameras:
    """Cameras around the origin, alternately above and below the equator, looking at it."""
    a = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    el = torch.tensor([0.4, -0.4] * (n // 2), dtype=torch.float64)
    eye = radius * torch.stack([el.cos() * a.cos(), el.cos() * a.sin(), el.sin()], -1)
    c2w = look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0, 0, 1.0], dtype=torch.float64))
    return Cameras(torch.full((n,), f), torch.full((n,), f), res / 2, res / 2, c2w, res, res)


def sphere_depth(cams: Cameras, r: float) -> torch.Tensor:
    """Exact z-depth of the sphere of radius ``r`` at the origin, 0 off it. ``# [N, H, W]``"""
    o, d = cams.image_rays(normalize=False)  # camera-frame z = 1 directions: t is the z-depth
    a, b, c = (d * d).sum(-1), 2 * (o * d).sum(-1), (o * o).sum(-1) - r * r
    disc = b * b - 4 * a * c
    return torch.where(disc > 0, (-b - disc.clamp_min(0).sqrt()) / (2 * a), torch.zeros_like(a)).float()


def test_tsdf_reproduces_a_sphere_within_a_voxel():
    cams, r = ring_cameras(), 0.8
    bounds = torch.tensor([[-1.0] * 3, [1.0] * 3])
    voxel = float((bounds[1] - bounds[0]).norm()) / 128
    volume = fuse(cams, sphere_depth(cams, r), bounds, voxel, 3 * voxel, chunk=100_000, bilinear=False)
    mesh = extract_mesh(volume)
    radial = np.abs(np.linalg.norm(mesh.vertices, axis=1) - r)
    assert radial.mean() < 0.3 * voxel and radial.max() < 1.5 * voxel  # no surface behind the truncation band
    sphere = trimesh.creation.icosphere(5, radius=r)
    c = geometry.mesh_chamfer(mesh, sphere, threshold=voxel, count=30_000)
    assert c["chamfer"] < voxel and c["fscore"] > 0.9, c
    outward = np.einsum("fc,fc->f", mesh.face_normals, mesh.triangles_center)
    assert (outward > 0).mean() > 0.99  # normals point to the free side


def test_unobserved_volume_gives_an_empty_mesh():
    cams = ring_cameras(2)
    volume = fuse(cams, torch.zeros(2, 64, 64), torch.tensor([[-1.0] * 3, [1.0] * 3]), 0.1, 0.3)
    assert len(extract_mesh(volume).faces) == 0 and volume.weight.sum() == 0


def test_shifted_cameras_move_along_x():
    cams = ring_cameras(2)
    out = shifted_cameras(cams, (0.0, 0.1), torch.zeros(3))
    assert len(out) == 4 and torch.equal(out.c2w[0], cams.c2w[0])
    step = out.centers[1] - cams.centers[0]
    assert torch.allclose(step, 0.1 * 3.0 * cams.R[0, :, 0]) and torch.equal(out.R[1], cams.R[0])


def test_mask_cleaning_drops_a_blob_outside_the_masks():
    cams = ring_cameras(4)
    main_sphere = trimesh.creation.icosphere(3, radius=0.5)
    blob = trimesh.creation.icosphere(2, radius=0.1).apply_translation([0.0, 0.0, 0.8])
    mesh = trimesh.util.concatenate([main_sphere, blob])
    masks = np.stack([geometry.silhouette(main_sphere, cams[i]) for i in range(len(cams))])
    masks = dilate_masks(masks, 0.1 * cams.width)  # rim vertices sit on the mask edge
    opts = MeshOptions(cull_hidden=False, min_component=0.0)
    clean, counts = clean_mesh(mesh, cams, masks, opts)
    assert np.linalg.norm(clean.vertices, axis=1).max() < 0.51  # the blob is gone
    assert len(clean.faces) == len(main_sphere.faces) and counts["in_masks"] == len(main_sphere.faces)
    # Without masks the component filter drops it instead (320 faces against the sphere's 1280).
    clean, _ = clean_mesh(mesh, cams, None, replace(opts, min_component=0.3))
    assert len(clean.faces) == len(main_sphere.faces)
    # Hidden-face culling keeps the visible outside of the sphere, drops a sphere inside it.
    inner = trimesh.creation.icosphere(2, radius=0.3)
    clean, _ = clean_mesh(trimesh.util.concatenate([main_sphere, inner]), cams, masks, MeshOptions(), supersample=4)
    assert np.linalg.norm(clean.vertices, axis=1).min() > 0.45


def test_hull_trim_drops_surface_one_view_sees_outside_its_mask():
    # a blob inside the masks of all views but one: the mask vote (2 views) keeps it, the visual hull
    # without slack drops it, one view of slack keeps it; the object itself always stays
    from omnirecon.mesh.clean import hull_trim, outside_votes

    cams = ring_cameras(4)
    main_sphere = trimesh.creation.icosphere(3, radius=0.5)
    masks = dilate_masks(np.stack([geometry.silhouette(main_sphere, cams[i]) for i in range(4)]), 0.1 * cams.width)
    for p in np.random.default_rng(0).uniform(-1.0, 1.0, (500, 3)):
        blob = trimesh.creation.icosphere(1, radius=0.03).apply_translation(p)
        out = outside_votes(np.asarray(blob.vertices), cams, masks)
        if out.min() == out.max() == 1:
            break
    else:
        raise AssertionError("no blob outside exactly one silhouette")
    mesh = trimesh.util.concatenate([main_sphere, blob])
    assert len(hull_trim(mesh, cams, masks, 0).faces) == len(main_sphere.faces)
    assert len(hull_trim(mesh, cams, masks, 1).faces) == len(mesh.faces)
    assert len(hull_trim(main_sphere, cams, masks, 0).faces) == len(main_sphere.faces)


def transformed(scene, T: torch.Tensor):
    """The same scene in a frame moved by the rigid ``T``; ``to_input`` absorbs the inverse."""
    corners = torch.cartesian_prod(*scene.bounds.double().T)  # [8, 3]
    moved = corners @ T[:3, :3].T + T[:3, 3]
    bounds = torch.stack([moved.min(0).values, moved.max(0).values]).float()
    return replace(scene, cameras=scene.cameras.transformed(T), bounds=bounds,
                   to_input=scene.to_input.double() @ torch.linalg.inv(T),
                   mesh_to_scene=T @ scene.mesh_to_scene.double())


def test_mesh_lands_on_the_ground_truth_in_the_input_frame(synth_scene, tmp_path):
    scene = load_at_resolution(synth_scene, 40)  # normalised: to_input scales and translates
    angle = 0.7
    T = torch.eye(4, dtype=torch.float64)
    T[:2, :2] = torch.tensor([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    T[:3, 3] = torch.tensor([0.3, -0.2, 0.1])
    scene = transformed(scene, T)
    assert not torch.allclose(scene.to_input, torch.eye(4, dtype=torch.float64), atol=0.1)
    views = scene.splits["train"]
    diag = float((scene.bounds[1] - scene.bounds[0]).norm())
    voxel = diag / 128
    volume = fuse(scene.cameras[views], scene.depths[views], scene.bounds, voxel, 3 * voxel, bilinear=False)
    mesh, _ = clean_mesh(extract_mesh(volume), scene.cameras[views], None, MeshOptions(cull_hidden=False))
    files = write_mesh(mesh, [tmp_path / f"m.{s}" for s in ("ply", "obj", "glb")], scene.to_input)
    gt = trimesh.load(scene.mesh_path, process=False)  # the generator's frame = the input frame
    scale = scene.scale_to_input
    gt_points = geometry.sample_points(gt, 100_000)
    for f in files:
        loaded = trimesh.load(f, process=False, force="mesh")
        assert len(loaded.vertices) == len(mesh.vertices) and len(loaded.faces) == len(mesh.faces)
        d = np.median(geometry.nearest_distances(np.asarray(loaded.vertices), gt_points))
        assert d < 0.5 * voxel * scale, f  # on the GT surface, in input units
    wrong = to_input_frame(mesh, torch.eye(4, dtype=torch.float64))  # the scene frame is not the input frame
    assert np.median(geometry.nearest_distances(wrong.vertices, gt_points)) > 5 * d


def test_to_input_frame_keeps_outward_winding_under_a_mirror():
    sphere = trimesh.creation.icosphere(2)
    mirrored = to_input_frame(sphere, torch.diag(torch.tensor([-2.0, 2.0, 2.0, 1.0], dtype=torch.float64)))
    assert mirrored.volume > 0 and mirrored.volume == pytest.approx(8 * sphere.volume)


def test_mesh_cli_floor(synth_scene, tmp_path, capsys, run_cli):
    out = tmp_path / "floor.ply"
    code, stdout, err = run_cli(["mesh", "--scene", synth_scene, "--model", "floor", "--out", out, tmp_path / "floor.glb",
                                 "--threads", 1, "--masks", "--depth", "model"])  # the floor's own depth
    assert code == 0, err
    assert out.is_file() and (tmp_path / "floor.glb").is_file() and (tmp_path / "floor_preview.png").is_file()
    record = json.loads((tmp_path / "floor_metrics.json").read_text())
    assert record["views"] == [0, 6, 11] and record["depth_maps"] == 3 and record["masks"]
    assert record["seconds"]["images_to_mesh"] >= record["seconds"]["render"] > 0
    m = record["metrics"]
    assert m["units"] == "input" and m["held_out"] == [14, 15]
    assert 0 < m["mask_iou"]["mean"] <= 1 and 0 <= m["chamfer"]["fscore"] <= 1 and "abs_rel" in m["depth"]
    assert m["rendered_depth"]["coverage"] > 0.5  # the floor's depth maps against the exact mesh
    assert len(trimesh.load(out, process=False).vertices) == record["vertices"] > 0
    assert "silhouette IoU" in stdout and "Chamfer" in stdout


def test_mesh_cli_random_ibrnet_checkpoint(synth_scene, tmp_path, capsys, run_cli):
    torch.manual_seed(0)
    ckpt = tmp_path / "ckpt"
    save_checkpoint(ckpt, build_model("ibrnet-tiny", TINY_IBRNET), "ibrnet-tiny", step=3)
    code, stdout, err = run_cli(["mesh", "--scene", synth_scene, "--ckpt", ckpt, "--views", 1, 2, 3, "--shifts", 0.0, 0.03, "--depth", "model",
                         "--min-acc", 0, "--no-masks", "--no-metrics", "--out", tmp_path / "ibr.obj"])
    assert code == 0, err
    assert (tmp_path / "ibr.obj").is_file() and not (tmp_path / "ibr_metrics.json").exists()
    assert "from 6 depth maps" in stdout


@pytest.mark.parametrize("args, message", [
    (["--ckpt", "{tmp}/nope"], "checkpoint folder not found"),
    (["--ckpt", "{tmp}"], "not a checkpoint folder"),
    (["--model", "floor", "--views", "1", "99"], "--views must name views in 0..15"),
    (["--model", "floor", "--out", "{tmp}/mesh.stl"], "cannot write a mesh as .stl"),
    (["--model", "floor", "--voxel", "0"], "--voxel"),
    (["--model", "floor", "--num-views", "50"], "--num-views must be in 1..12"),
    ([], "exactly one of --ckpt or --model"),
])
def test_mesh_bad_input_exit_2(args, message, synth_scene, tmp_path, capsys, run_cli):
    args = [a.format(tmp=tmp_path) for a in args]
    code, stdout, err = run_cli(["mesh", "--scene", synth_scene, *args])
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("omnirecon: error:") and message in lines[0], err


def test_reference_preset_is_settings_of_the_one_pipeline(synth_scene):
    """VolRecon's protocol (`--fusion reference`) runs through the same stages with its own settings."""
    from omnirecon.mesh.build import PRESETS, mesh_from_model

    scene = load_at_resolution(synth_scene, 40)
    views = scene.splits["train"][:6]
    opts = MeshOptions.preset("reference", depth="oracle")
    assert opts.voxel == PRESETS["reference"]["voxel"] and not opts.bilinear and not opts.complete
    made = mesh_from_model(None, scene, views, opts, use_masks=True)
    assert made.info["options"]["fusion"] == "reference" and "in_masks" in made.info["faces"]
    assert made.info["completion"] is None and len(made.mesh.faces) > 100
    gt = geometry.ground_truth_mesh(scene, objects_only=True)
    c = geometry.mesh_chamfer(made.mesh, gt, threshold=0.02 * float((scene.bounds[1] - scene.bounds[0]).norm()),
                              count=20_000)
    assert c["precision"] > 0.8, c
