"""``omnirecon synth``: determinism, exact geometry, multi-view consistency, framing, bad flags.

Scenes are tiny (64 x 64, 12 views) and generated once per module; every geometric check goes
through the public reader (``omnirecon.data.load_scene``) and the GT mesh file.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from omnirecon.cli import main as cli_main
from omnirecon.commands.synth import SynthCommand
from omnirecon.data import load_scene
from omnirecon.data.synth import SynthOptions, generate_scene, rigs
from omnirecon.data.synth.generate import build_mesh
from omnirecon.data.synth.layout import GROUND_ID, make_layout
from omnirecon.errors import InputError
from omnirecon.render.zbuffer import rasterize

RIGS = ("object", "frontal", "forward")
RES, VIEWS = 64, 12


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("synth")
    return {rig: generate_scene(out / rig, 11, SynthOptions(rig=rig, views=VIEWS, resolution=RES)) for rig in RIGS}


def _hashes(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _mesh(scene) -> trimesh.Trimesh:
    return trimesh.load(scene.mesh_path, process=False)


def _surface_pixels(scene, view: int, count: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` random pixel centres with a surface behind them: ``uv # [count, 2]``, ``depth # [count]``."""
    depth = scene.depths[view].double()
    ii, jj = torch.nonzero(depth > 0, as_tuple=True)
    pick = torch.randperm(len(ii), generator=torch.Generator().manual_seed(seed))[:count]
    uv = torch.stack([jj[pick], ii[pick]], dim=-1).double() + 0.5
    return uv, depth[ii[pick], jj[pick]]


def _closest_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Distance from each point to the mesh, against every triangle (no spatial index needed). ``# [P]``"""
    tris = mesh.triangles  # [F, 3, 3]
    best = np.full(len(points), np.inf)
    for i, p in enumerate(points):
        closest = trimesh.triangles.closest_point(tris, np.broadcast_to(p, (len(tris), 3)))
        best[i] = np.linalg.norm(closest - p, axis=1).min()
    return best


def _ray_depth(mesh: trimesh.Trimesh, origin: np.ndarray, direction: np.ndarray) -> float:
    """Distance to the first hit of one ray with the mesh, by plane intersection + barycentric test."""
    tris = mesh.triangles
    n = len(tris)
    hits, ok = trimesh.intersections.planes_lines(
        plane_origins=tris[:, 0], plane_normals=mesh.face_normals,
        line_origins=np.broadcast_to(origin, (n, 3)), line_directions=np.broadcast_to(direction, (n, 3)))
    bary = trimesh.triangles.points_to_barycentric(tris[ok], hits)
    inside = (bary >= -1e-9).all(axis=1)
    t = (hits[inside] - origin) @ direction
    return float(t[t > 0].min())


def test_same_seed_gives_identical_files(tmp_path):
    options = SynthOptions(rig="object", views=4, resolution=32, max_objects=3)
    a = generate_scene(tmp_path / "a", 5, options)
    b = generate_scene(tmp_path / "b", 5, options)
    c = generate_scene(tmp_path / "c", 6, options)
    assert _hashes(a) == _hashes(b)
    assert _hashes(a) != _hashes(c)
    assert not list(tmp_path.glob("*/.scene_*")), "temporary folders left behind"


def test_cached_scene_is_reused_only_with_the_same_options(tmp_path):
    options = SynthOptions(rig="object", views=4, resolution=32, max_objects=3)
    path = generate_scene(tmp_path, 5, options)
    stamp = (path / "scene.json").stat().st_mtime_ns
    assert generate_scene(tmp_path, 5, options) == path
    assert (path / "scene.json").stat().st_mtime_ns == stamp, "an identical cached scene was rewritten"
    generate_scene(tmp_path, 5, replace(options, resolution=24, views=5))  # same folder, other options
    scene = load_scene(path)
    assert (scene.width, scene.height) == (24, 24) and len(scene) == 5
    assert json.loads((path / "scene.json").read_text())["options"]["resolution"] == 24


@pytest.mark.parametrize("rig", RIGS)
def test_depth_lies_on_the_mesh(scenes, rig):
    scene = load_scene(scenes[rig])
    mesh = _mesh(scene)
    extent = float(np.linalg.norm(mesh.extents))
    uv, depth = _surface_pixels(scene, 1, 40)
    points = scene.cameras[1].unproject(uv[None], depth[None])[0].numpy()  # [P, 3]
    dist = _closest_distance(mesh, points)
    assert dist.max() < 1e-3 * extent, f"max distance {dist.max():.2e} (extent {extent:.2f})"


@pytest.mark.parametrize("rig", RIGS)
def test_ray_cast_depth_matches(scenes, rig):
    scene = load_scene(scenes[rig])
    step = json.loads((scenes[rig] / "transforms_train.json").read_text())["depth_scale"]
    mesh = _mesh(scene)
    uv, depth = _surface_pixels(scene, 2, 8, seed=1)
    origins, dirs = scene.cameras[2].rays(uv[None], normalize=False)  # camera-z = 1 directions
    for o, d, z in zip(origins[0].numpy(), dirs[0].numpy(), depth.numpy()):
        t = _ray_depth(mesh, o, d / np.linalg.norm(d)) / np.linalg.norm(d)  # distance -> z-depth
        assert abs(t - z) <= 0.5 * step + 1e-6 * z, (t, z)  # 16-bit quantisation only


def test_rendered_depth_is_exact_before_quantisation(tmp_path):
    """The rasterizer's float depth equals an independent ray cast against the PLY to float64 precision."""
    layout = make_layout(np.random.default_rng(3), "object", 2, True, (3, 4))
    mesh = build_mesh(layout, texture_size=64)
    ply = tmp_path / "mesh.ply"
    ply.write_bytes(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(file_type="ply"))
    loaded = trimesh.load(ply, process=False)
    assert np.array_equal(loaded.vertices, mesh.vertices)  # float32 vertices survive the PLY exactly
    K = rigs.intrinsics(layout.fov, 48, 48)
    c2w = layout.c2w[1]
    frags = rasterize(mesh.vertices, mesh.faces, K, np.linalg.inv(c2w), 48, 48)
    ii, jj = np.nonzero(frags.depth > 0)
    for i, j in list(zip(ii, jj))[::97][:12]:
        ray = c2w[:3, :3] @ np.array([(j + 0.5 - K[0, 2]) / K[0, 0], (i + 0.5 - K[1, 2]) / K[1, 1], 1.0])
        z = _ray_depth(loaded, c2w[:3, 3], ray / np.linalg.norm(ray)) / np.linalg.norm(ray)
        assert abs(z - frags.depth[i, j]) < 1e-9 * z


def _warp_error(scene, src: int, dst: int) -> tuple[float, int]:
    """Mean |colour difference| of ``src`` pixels warped into ``dst`` by depth, over co-visible pixels."""
    cams = scene.cameras
    h, w = scene.height, scene.width
    uv = cams.pixel_centers().reshape(1, -1, 2)
    depth = scene.depths[src].reshape(1, -1).double()
    points = cams[src].unproject(uv, depth)[0]  # [HW, 3]
    proj = cams[dst].project(points)
    uv_dst, z_dst = proj.uv[0], proj.depth[0]  # [HW, 2], [HW]
    ij = uv_dst.floor().long()
    inside = proj.in_image[0] & (depth[0] > 0)
    ij = ij.clamp(min=torch.zeros(2, dtype=torch.long), max=torch.tensor([w - 1, h - 1]))
    z_seen = scene.depths[dst][ij[:, 1], ij[:, 0]].double()
    visible = inside & ((z_seen - z_dst).abs() < 0.01 * z_dst)
    grid = (uv_dst / torch.tensor([w, h]) * 2 - 1).float()[visible][None, None]  # +0.5 convention
    sampled = torch.nn.functional.grid_sample(
        scene.images[dst].permute(2, 0, 1)[None], grid, align_corners=False, mode="bilinear")[0, :, 0].T
    err = (sampled - scene.images[src].reshape(-1, 3)[visible]).abs().mean()
    return float(err), int(visible.sum())


@pytest.mark.parametrize("rig", RIGS)
def test_depth_warp_photometric_consistency(scenes, rig):
    scene = load_scene(scenes[rig])
    centres = scene.cameras.centers
    errors, control = [], []
    for src in range(0, len(scene), 3):
        d = (centres - centres[src]).norm(dim=-1)
        d[src] = float("inf")
        dst = int(d.argmin())
        err, count = _warp_error(scene, src, dst)
        assert count > 0.2 * (scene.depths[src] > 0).sum()
        errors.append(err)
        # control: the same warp with the target camera moved sideways by about one pixel
        depth = float(scene.depths[dst][scene.depths[dst] > 0].mean())
        c2w = scene.cameras.c2w.clone()
        c2w[dst, :3, 3] += depth / float(scene.cameras.fx[dst]) * c2w[dst, :3, 0]
        moved = replace(scene, cameras=replace(scene.cameras, c2w=c2w))
        control.append(_warp_error(moved, src, dst)[0])
    print(f"{rig}: depth-warp MAE {np.mean(errors):.4f} (max {np.max(errors):.4f}); "
          f"camera moved by 1 px: {np.mean(control):.4f}")
    assert np.mean(errors) < 0.03
    assert np.mean(control) > 1.5 * np.mean(errors)


@pytest.mark.parametrize("rig", RIGS)
def test_normals_match_mesh_and_depth_gradient(scenes, rig):
    scene = load_scene(scenes[rig])
    mesh = _mesh(scene)
    view = 3
    normals = scene.normals[view]  # [H, W, 3]
    # the file holds 0,0,0 exactly where there is no surface
    raw = np.asarray(Image.open(scenes[rig] / f"{scene.names[view][:-4]}_normal.png"))
    assert np.array_equal(raw.any(-1), scene.depths[view].numpy() > 0)
    assert torch.equal(normals.norm(dim=-1) > 0, scene.depths[view] > 0)
    assert (normals.norm(dim=-1)[scene.depths[view] > 0] - 1).abs().max() < 1e-5
    # normals face the camera
    uv = scene.cameras.pixel_centers()[None]
    _, dirs = scene.cameras[view].rays(uv)
    facing = (normals * dirs[0].float()).sum(-1)
    assert (facing[scene.depths[view] > 0] < 0.05).all()
    # normal of the mesh triangle at the unprojected point (8-bit quantisation: < 1 degree)
    uv_s, depth = _surface_pixels(scene, view, 30, seed=2)
    points = scene.cameras[view].unproject(uv_s[None], depth[None])[0].numpy()
    tris = mesh.triangles
    for p, (u, v) in zip(points, uv_s.long().tolist()):
        closest = trimesh.triangles.closest_point(tris, np.broadcast_to(p, (len(tris), 3)))
        dist = np.linalg.norm(closest - p, axis=1)
        candidates = np.flatnonzero(dist < dist.min() + 1e-6 * np.linalg.norm(mesh.extents))
        cos = mesh.face_normals[candidates] @ normals[v, u].double().numpy()
        assert cos.max() > np.cos(np.radians(1.5))
    # depth gradient: the plane through 3 neighbouring unprojected points has the stored normal
    pts = scene.cameras[view].unproject(uv, scene.depths[view][None].double())[0]  # [H, W, 3]
    du = pts[1:-1, 2:] - pts[1:-1, :-2]
    dv = pts[2:, 1:-1] - pts[:-2, 1:-1]
    n_depth = torch.nn.functional.normalize(torch.cross(dv, du, dim=-1), dim=-1).float()
    n_stored = normals[1:-1, 1:-1]
    lab = scene.labels[view]
    same = torch.ones_like(lab[1:-1, 1:-1], dtype=torch.bool)
    for di, dj in ((0, 1), (0, -1), (1, 0), (-1, 0)):  # away from object borders
        same &= lab[1 + di:lab.shape[0] - 1 + di, 1 + dj:lab.shape[1] - 1 + dj] == lab[1:-1, 1:-1]
    smooth = same & (lab[1:-1, 1:-1] > 0)
    agree = ((n_depth * n_stored).sum(-1).abs() > np.cos(np.radians(10)))[smooth].float().mean()
    assert agree > 0.9, f"only {agree:.2f} of pixels agree with the depth gradient"


@pytest.mark.parametrize("rig", RIGS)
def test_labels_masks_and_framing(scenes, rig):
    scene = load_scene(scenes[rig])
    labels, masks = scene.labels, scene.masks
    assert torch.equal(masks, (labels > 0) & (labels != GROUND_ID))
    assert torch.equal(labels > 0, scene.depths > 0)
    meta = json.loads((scenes[rig] / "scene.json").read_text())
    prims = meta["primitives"]
    assert len(prims) >= 2 and {p["id"] for p in prims} == set(range(1, len(prims) + 1))
    # every primitive is seen, entirely inside the image, in most views
    mesh = _mesh(scene)
    raw = mesh.metadata["_ply_raw"]["face"]["data"]["object_id"]
    for prim in prims:
        verts = mesh.vertices[np.unique(mesh.faces[raw == prim["id"]])]
        proj = scene.cameras.project(torch.from_numpy(verts))
        framed = proj.in_image.all(dim=1).float().mean()
        assert framed > 0.75, f"{prim['type']} {prim['id']} framed in only {framed:.0%} of views"
    seen = torch.stack([(labels == p["id"]).flatten(1).any(1) for p in prims]).float().mean()
    assert seen > 0.6
    # near/far cover all depths; aabb holds the mesh
    d = scene.depths[scene.depths > 0]
    assert scene.near.min() <= d.min() and d.max() <= scene.far.max()
    assert (scene.bounds[0] <= torch.from_numpy(mesh.vertices.min(0)).float() + 1e-5).all()


def _target(folder: Path) -> torch.Tensor:
    return torch.tensor(json.loads((folder / "scene.json").read_text())["rig_params"]["target"], dtype=torch.float64)


def test_rigs_have_their_shape(scenes):
    obj = load_scene(scenes["object"])
    target = _target(scenes["object"])
    radius = (obj.cameras.centers - target).norm(dim=-1)
    assert (radius.max() - radius.min()) < 1e-6 * radius.max()  # one sphere
    looks = torch.nn.functional.normalize(target - obj.cameras.centers, dim=-1)
    assert ((looks * obj.cameras.forward).sum(-1) > 0.9999).all()  # at its centre
    assert (obj.cameras.centers[:, 2] > target[2]).all()  # upper hemisphere (there is a ground)

    frontal = load_scene(scenes["frontal"])
    target = _target(scenes["frontal"])
    offsets = frontal.cameras.centers - target
    flat = torch.nn.functional.normalize(offsets[:, :2], dim=-1)
    mean = torch.nn.functional.normalize(flat.mean(0), dim=0)
    azimuth = torch.rad2deg(torch.arccos((flat @ mean).clamp(-1, 1)))
    assert 30 < azimuth.max() < 45  # an arc of about +-40 degrees
    radius = offsets.norm(dim=-1)
    assert radius.max() / radius.min() < 1.11  # similar distances
    looks = torch.nn.functional.normalize(target - frontal.cameras.centers, dim=-1)
    assert ((looks * frontal.cameras.forward).sum(-1) > 0.9999).all()

    fwd = load_scene(scenes["forward"])
    assert fwd.rig == "forward"
    axes = fwd.cameras.forward
    assert ((axes @ axes[0]) > 0.9999).all()  # parallel optical axes
    spread = (fwd.cameras.centers - fwd.cameras.centers.mean(0)) @ axes[0]
    assert spread.abs().max() < 1e-6  # on one plane facing the scene


@pytest.mark.parametrize("argv, message", [
    (["--views", "0"], "--views"),
    (["--resolution", "4"], "--resolution"),
    (["--num-scenes", "0"], "--num-scenes"),
    (["--workers", "0"], "--workers"),
    (["--min-objects", "5", "--max-objects", "2"], "objects"),
])
def test_bad_flags_raise_input_error(tmp_path, argv, message, capsys):
    flags = {a.lstrip("-").replace("-", "_"): int(b) for a, b in zip(argv[::2], argv[1::2])}
    with pytest.raises(InputError, match=message):
        SynthCommand(out=tmp_path, **flags).main()
    assert cli_main(["synth", "--out", str(tmp_path), *argv]) == 2
    assert "omnirecon: error:" in capsys.readouterr().err


def test_cli_writes_scenes(tmp_path):
    code = cli_main(["synth", "--out", str(tmp_path), "--num-scenes", "2", "--seed", "3", "--views", "3",
                     "--resolution", "16", "--workers", "1", "--rig", "forward", "--no-ground"])
    assert code == 0
    # the scenes, and the marker that says omnirecon wrote this folder (outputs.claim)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".omnirecon-output.json", "scene_00003", "scene_00004"]
    scene = load_scene(tmp_path / "scene_00004")
    assert scene.rig == "forward" and len(scene) == 3 and not (scene.labels == GROUND_ID).any()
