"""Every reader on the real scenes it applies to, plus synthetic fixtures for the formats without
sample data (MVSNet, COLMAP) and for the Blender extension used by procedural scenes."""

import functools
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import shared_scene

from omnirecon.cameras import Cameras, closest_point_to_axes, look_at
from omnirecon.data import ReadOptions, detect_format, load_scene
from omnirecon.data._common import distort
from omnirecon.data.colmap_io import (
    Camera,
    Image,
    Model,
    Points,
    qvec_to_rotmat,
    read_model,
    rotmat_to_qvec,
    write_model,
)
from omnirecon.data.dtu_mvsnet import write_mvsnet
from omnirecon.data.io import write_image, write_json

SCENES = {
    "blender/lego": "blender", "blender/chair": "blender", "instant_ngp/fox": "ngp",
    "llff/fern": "llff", "llff/ethiopianHead": "llff",
    "neus_dtu/dtu_scan24": "dtu_neus", "neus_dtu/dtu_scan37": "dtu_neus",
}


@functools.lru_cache(maxsize=None)
def _cached(rel, downscale=1.0, splits=None, max_views=None):
    return load_scene(shared_scene(rel), options=ReadOptions(downscale=downscale, splits=splits, max_views=max_views))


def scene(rel, downscale=1.0, splits=None, max_views=None):
    shared_scene(rel)  # skip (uncached) when absent
    return _cached(rel, downscale, splits, max_views)


def hull_fraction(s, view=0, rays=200, steps=96, agree=0.9, seed=0):
    """Fraction of view ``view``'s foreground rays with a point (between near and far) that falls
    inside the masks of at least ``agree`` of the other views that see it."""
    g = torch.Generator().manual_seed(seed)
    fg = s.masks[view].nonzero().double() + 0.5  # [F, 2] (row, col) centres
    uv = fg[torch.randint(len(fg), (rays,), generator=g)].flip(-1)  # [R, 2]
    cam = s.cameras[view]
    z = torch.linspace(float(s.near[view]), float(s.far[view]), steps, dtype=torch.float64)
    pts = cam.unproject(uv[None].expand(1, rays, 2)[:, :, None].expand(1, rays, steps, 2).reshape(1, -1, 2),
                        z.repeat(rays)[None])[0]  # [R*S, 3]
    others = [i for i in range(len(s)) if i != view]
    p = s.cameras[others].project(pts)
    col = p.uv[..., 0].floor().long().clamp(0, s.width - 1)
    row = p.uv[..., 1].floor().long().clamp(0, s.height - 1)
    inside = s.masks[others][torch.arange(len(others))[:, None], row, col] & p.in_image  # [V, R*S]
    ratio = inside.sum(0) / p.in_image.sum(0).clamp_min(1)
    ok = (ratio >= agree) & (p.in_image.sum(0) >= 3)
    return ok.reshape(rays, steps).any(1).double().mean().item()


# ---------------------------------------------------------------------- detection and basics
@pytest.mark.parametrize("rel,fmt", SCENES.items())
def test_detect_format(rel, fmt):
    assert detect_format(shared_scene(rel)) == fmt


@pytest.mark.parametrize("rel", SCENES)
def test_scene_is_valid(rel):
    s = scene(rel, downscale=8)
    s.validate()
    assert s.images.dtype == torch.float32 and s.images.shape[-1] == 3
    assert 0 <= float(s.images.min()) and float(s.images.max()) <= 1
    assert len(s.cameras) == len(s) == len(s.near) == len(s.far) == len(s.names)
    assert s.bounds.shape == (2, 3) and (s.bounds[1] > s.bounds[0]).all()
    assert (s.near > 0).all() and (s.far > s.near).all()
    assert s.rig in ("object", "forward")
    # the cameras look at the content: the centre of the bounds lies in front of every camera
    assert s.cameras.project(s.bounds.double().mean(0)[None]).in_front.all()


@pytest.mark.parametrize("rel,counts", [
    ("blender/lego", {"all": 400, "train": 100, "val": 100, "test": 200}),
    ("blender/chair", {"all": 400, "train": 100, "val": 100, "test": 200}),
    ("instant_ngp/fox", {"all": 67, "train": 58, "test": 9}),
    ("llff/fern", {"all": 20, "train": 17, "test": 3}),
    ("llff/ethiopianHead", {"all": 66, "train": 57, "test": 9}),
    ("neus_dtu/dtu_scan24", {"all": 49, "train": 41, "test": 8}),
])
def test_split_counts(rel, counts):
    s = scene(rel, downscale=8)
    assert {k: len(v) for k, v in s.splits.items()} == counts
    if "test" in s.splits and "val" not in s.splits and s.format != "dtu_neus":
        assert s.splits["test"][:3] == [0, 8, 16][:len(s.splits["test"])]


# ---------------------------------------------------------------------- blender
def test_blender_lego_cameras_and_images():
    s = scene("blender/lego", splits=("val",), max_views=8)
    assert (s.width, s.height) == (400, 400) and len(s) == 8
    assert torch.allclose(s.cameras.fx, torch.tensor(555.5555, dtype=torch.float64), atol=0.01)
    assert torch.allclose(s.cameras.cx, torch.tensor(200.0, dtype=torch.float64))
    assert s.masks is not None and s.background == (1.0, 1.0, 1.0)
    bg = s.images[~s.masks]  # alpha <= 0.5: at least half white
    assert (bg >= 0.5).all() and (bg == 1).all(-1).double().mean() > 0.95
    assert s.depths is None  # the upstream 8-bit depth visualisations are not depth
    assert s.near[0] == 2 and s.far[0] == 6


@pytest.mark.parametrize("rel", ["blender/lego", "blender/chair"])
def test_blender_radius_and_look_at_origin(rel):
    s = scene(rel, downscale=8)
    assert (s.cameras.centers.norm(dim=-1) - 4.0311).abs().max() < 1e-3
    uv = s.cameras.project(torch.zeros(1, 3)).uv[:, 0]  # the origin is the image centre
    assert ((uv - torch.tensor([s.width / 2, s.height / 2])).abs() < 0.05 * s.width).all()


def test_blender_black_background():
    s = load_scene(shared_scene("blender/chair"), options=ReadOptions(downscale=4, splits=("test",), max_views=2,
                                                                     background="black"))
    assert s.background == (0.0, 0.0, 0.0) and float(s.images[~s.masks].max()) <= 0.5
    assert (s.images[~s.masks] == 0).all(-1).double().mean() > 0.95


def test_blender_masks_agree_through_the_hull():
    s = scene("blender/lego", downscale=4, splits=("train",))
    assert hull_fraction(s) > 0.95


# ---------------------------------------------------------------------- instant-ngp
def test_ngp_fox():
    s = scene("instant_ngp/fox")
    assert len(s) == 67 and (s.width, s.height) == (225, 400)
    assert float(s.cameras.fx[0]) == pytest.approx(286.5667, abs=1e-3)
    assert float(s.cameras.cy[0]) == pytest.approx(201.0975, abs=1e-3)
    centre = closest_point_to_axes(s.cameras)
    assert s.cameras.project(centre[None]).in_image.all()
    assert ((centre >= s.bounds[0]) & (centre <= s.bounds[1])).all()
    assert s.rig == "object" and (s.near < s.cameras.project(centre[None]).depth[:, 0]).all()
    # the distortion was removed: the corners, which sample outside the distorted image, are black
    assert float(s.images[:, 0, 0].max()) == 0 and float(s.images[:, s.height // 2, s.width // 2].max()) > 0


# ---------------------------------------------------------------------- LLFF
def test_llff_fern():
    s = scene("llff/fern")
    assert (s.width, s.height) == (336, 252) and s.rig == "forward"
    assert float(s.cameras.fx[0]) == pytest.approx(271.71, abs=0.01)
    assert float(s.near.min()) == pytest.approx(16.985, abs=0.01)
    assert float(s.far.max()) == pytest.approx(80.0, abs=0.01)
    f = s.cameras.forward
    assert (f @ f.T).min() > 0.9  # all optical axes roughly parallel, pointing the same way
    # points at mid-depth on each axis: their mean lies in front of, and inside, every view
    mid = (s.cameras.centers + f * ((s.near + s.far) / 2)[:, None]).mean(0)
    assert s.cameras.project(mid[None]).in_image.all()
    # the y axis points down in the image: the world "up" of the capture (-mean y) projects above the centre
    up = -s.cameras.R[:, :, 1].mean(0)
    uv = s.cameras.project((mid + 5 * up)[None]).uv[:, 0]
    assert (uv[:, 1] < s.height / 2).all()


def test_llff_ethiopian_head():
    s = scene("llff/ethiopianHead", downscale=2)
    assert (s.width, s.height) == (200, 200) and s.rig == "object"
    full = scene("llff/ethiopianHead", max_views=2)
    assert float(full.cameras.fx[0]) == pytest.approx(754.36, abs=0.01)
    assert s.masks is not None and s.masks.float().mean() > 0.05
    centre = closest_point_to_axes(s.cameras)
    assert s.cameras.project(centre[None]).in_image.all()
    assert ((centre >= s.bounds[0]) & (centre <= s.bounds[1])).all()
    assert hull_fraction(s, view=5) > 0.95


# ---------------------------------------------------------------------- DTU (NeuS)
@pytest.mark.parametrize("rel", ["neus_dtu/dtu_scan24", "neus_dtu/dtu_scan37"])
def test_dtu_neus(rel):
    s = scene(rel, downscale=2)
    full = scene(rel, max_views=1)
    K = full.cameras.K[0]
    assert float(K[0, 0]) == pytest.approx(723.08, abs=0.01) and float(K[1, 1]) == pytest.approx(720.79, abs=0.01)
    assert float(K[0, 2]) == pytest.approx(205.80, abs=0.01) and float(K[1, 2]) == pytest.approx(154.77, abs=0.01)
    assert len(s) == 49 and s.masks is not None and s.rig == "object"
    assert torch.equal(s.bounds, torch.tensor([[-1.0] * 3, [1.0] * 3]))
    scale = {"neus_dtu/dtu_scan24": 231.07, "neus_dtu/dtu_scan37": 256.05}[rel]
    assert s.scale_to_input == pytest.approx(scale, abs=0.01)
    assert hull_fraction(s) > 0.95 and hull_fraction(s, view=30) > 0.95


def test_hull_check_detects_wrong_poses():
    """Negative control for :func:`hull_fraction`: inverted or permuted poses fail it."""
    s = scene("neus_dtu/dtu_scan24", downscale=2)
    c = s.cameras
    inverted = Cameras(c.fx, c.fy, c.cx, c.cy, c.w2c, c.width, c.height)  # the classic c2w/w2c mix-up
    reversed_ = Cameras(c.fx, c.fy, c.cx, c.cy, c.c2w.flip(0), c.width, c.height)
    assert hull_fraction(replace(s, cameras=inverted)) < 0.5
    assert hull_fraction(replace(s, cameras=reversed_)) < 0.9


def test_dtu_projection_matches_npz():
    path = shared_scene("neus_dtu/dtu_scan24")
    s = scene("neus_dtu/dtu_scan24", max_views=3)
    npz = np.load(path / "cameras_sphere.npz")
    pts = torch.rand(50, 3, dtype=torch.float64) - 0.5
    for j, i in enumerate([0, 24, 48]):
        P = torch.from_numpy(npz[f"world_mat_{i}"].astype(np.float64) @ npz[f"scale_mat_{i}"])
        h = torch.cat([pts, torch.ones(50, 1, dtype=torch.float64)], 1) @ P.T
        ref = h[:, :2] / h[:, 2:3]
        assert torch.allclose(s.cameras[j].project(pts).uv[0], ref, atol=1e-3)  # float32 npz: skew ~1e-4 px dropped


# ---------------------------------------------------------------------- options
def test_downscale_scales_intrinsics_exactly():
    a = scene("neus_dtu/dtu_scan24", max_views=3)
    for ds in (2, 3):
        b = load_scene(shared_scene("neus_dtu/dtu_scan24"), options=ReadOptions(downscale=ds, max_views=3))
        assert (b.width, b.height) == (round(400 / ds), round(300 / ds))
        sx, sy = b.width / a.width, b.height / a.height
        assert torch.allclose(b.cameras.fx, a.cameras.fx * sx) and torch.allclose(b.cameras.cy, a.cameras.cy * sy)
        rel = torch.rand(3, 20, 2, dtype=torch.float64)
        da = a.cameras.rays(rel * torch.tensor([a.width, a.height]))[1]
        db = b.cameras.rays(rel * torch.tensor([b.width, b.height]))[1]
        assert torch.allclose(da, db, atol=1e-12)
    b = load_scene(shared_scene("neus_dtu/dtu_scan24"), options=ReadOptions(downscale=2, max_views=3))
    pooled = torch.nn.functional.avg_pool2d(a.images.permute(0, 3, 1, 2), 2).permute(0, 2, 3, 1)
    assert (pooled - b.images).abs().max() < 1.01 / 255  # area averaging


def test_llff_downscale_uses_factor_folders():
    s = scene("llff/fern", downscale=2, max_views=2)
    assert (s.width, s.height) == (168, 126)
    assert float(s.cameras.fx[0]) == pytest.approx(271.7105 / 2, abs=1e-3)


def test_max_views_and_splits():
    s = scene("instant_ngp/fox", downscale=4, max_views=5)
    assert len(s) == 5 and s.names[0] == "images/0001.jpg"
    assert set(sum(s.splits.values(), [])) <= set(range(5))
    t = scene("blender/lego", downscale=8, splits=("test",))
    assert len(t) == 200 and set(t.splits) == {"all", "test"}
    with pytest.raises(Exception, match="no split 'nope'"):
        scene("blender/lego", downscale=8, splits=("nope",))


# ---------------------------------------------------------------------- MVSNet (converted from DTU)
@pytest.mark.parametrize("layout", ["test", "train"])
def test_dtu_mvsnet_round_trip(tmp_path, layout):
    neus = scene("neus_dtu/dtu_scan24", downscale=4, max_views=6)
    root = write_mvsnet(neus, tmp_path / "scan24", layout=layout, scan="scan24")
    assert detect_format(root) == "dtu_mvsnet"
    m = load_scene(root)
    ref = neus.cameras.transformed(neus.to_input)  # DTU world units (mm)
    assert m.format == "dtu_mvsnet" and len(m) == 6 and m.rig == "object"
    assert torch.allclose(m.cameras.c2w, ref.c2w, atol=1e-9)
    assert torch.allclose(m.cameras.K, ref.K, atol=1e-9)
    assert torch.allclose(m.near, neus.near * neus.scale_to_input)
    assert torch.allclose(m.far, neus.far * neus.scale_to_input)
    assert (m.images - neus.images).abs().max() < 0.6 / 255
    assert len(m.meta["pairs"]["0"]) == 5 and 0 not in m.meta["pairs"]["0"]
    if layout == "train":  # the scan folder itself is a valid path too
        assert len(load_scene(root / "Rectified" / "scan24")) == 6
    # the unit sphere's centre (the scan) projects inside every image
    assert m.cameras.project(neus.to_input[:3, 3][None]).in_image.all()


# ---------------------------------------------------------------------- COLMAP
def test_quaternion_convention():
    th = 0.3
    R = qvec_to_rotmat(np.array([math.cos(th / 2), 0, 0, math.sin(th / 2)]))
    assert np.allclose(R, [[math.cos(th), -math.sin(th), 0], [math.sin(th), math.cos(th), 0], [0, 0, 1]])
    g = np.random.default_rng(0)
    for _ in range(20):
        q = g.normal(size=4)
        q = q / np.linalg.norm(q) * np.sign(q[0])
        assert np.allclose(rotmat_to_qvec(qvec_to_rotmat(q)), q, atol=1e-12)


def colmap_from_scene(s, model="PINHOLE", extra=(), n_points=1500, seed=0):
    """A COLMAP model of ``s``'s cameras, with points drawn in the unit ball and observed where they project."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(n_points, 3, generator=g, dtype=torch.float64)
    pts = pts / pts.norm(dim=1, keepdim=True) * torch.rand(n_points, 1, generator=g, dtype=torch.float64) ** (1 / 3)
    proj = s.cameras.project(pts)
    cams, images, tracks = {}, [], [[] for _ in range(n_points)]
    for i in range(len(s)):
        c = s.cameras[i]
        f = [float(c.fx[0]), float(c.fy[0]), float(c.cx[0]), float(c.cy[0])]
        params = {"PINHOLE": f, "SIMPLE_PINHOLE": [f[0], f[2], f[3]]}.get(model, [*f, *extra])
        cams[i + 1] = Camera(i + 1, model, s.width, s.height, np.array(params))
        w2c = c.w2c[0].numpy()
        vis = proj.in_image[i].nonzero()[:, 0].numpy()
        for k, p in enumerate(vis):
            tracks[p].append((i + 1, k))
        images.append(Image(i + 1, rotmat_to_qvec(w2c[:3, :3]), w2c[:3, 3].copy(), i + 1, f"view_{i:03d}.png",
                            proj.uv[i, vis].numpy(), vis.astype(np.int64) + 100))
    points = Points(np.arange(n_points, dtype=np.int64) + 100, pts.numpy(),
                    np.full((n_points, 3), 128, np.uint8), np.full(n_points, 0.5),
                    [np.array(t, np.int64).reshape(-1, 2) for t in tracks])
    return Model(cams, images, points, None, None)


@pytest.mark.parametrize("ext", [".txt", ".bin"])
def test_colmap_round_trip(tmp_path, ext):
    s = scene("neus_dtu/dtu_scan24", downscale=4, max_views=10)
    model = colmap_from_scene(s)
    write_model(model, tmp_path / "sparse" / "0", ext)
    for i in range(len(s)):
        write_image(tmp_path / "images" / f"view_{i:03d}.png", s.images[i].numpy())
    back = read_model(tmp_path / "sparse" / "0", ext)
    assert [im.name for im in back.images] == [im.name for im in model.images]
    assert np.array_equal(back.points.ids, model.points.ids) and np.allclose(back.points.xyz, model.points.xyz)
    assert all(np.array_equal(a, b) for a, b in zip(back.points.tracks, model.points.tracks))
    assert detect_format(tmp_path) == "colmap"
    c = load_scene(tmp_path)
    assert c.format == "colmap" and len(c) == 10
    # the scene frame is upright and unit-scaled; to_input maps it back onto the model's frame exactly
    back_cams = c.cameras.transformed(c.to_input)
    assert torch.allclose(back_cams.c2w, s.cameras.c2w, atol=1e-6)
    assert torch.allclose(c.cameras.K, s.cameras.K, atol=1e-6)
    assert (c.images - s.images).abs().max() < 0.6 / 255
    up = c.cameras.c2w[:, :3, 1].mean(0)  # OpenCV y is down: the mean points to -z
    assert up[2] < -0.9 * up.norm()
    # points project onto their stored observations (the pose convention round-trips)
    for i, im in enumerate(model.images):
        uv = back_cams[i].project(torch.from_numpy(model.points.xyz[im.point3D_ids - 100])).uv[0]
        assert torch.allclose(uv, torch.from_numpy(im.xys), atol=1e-6)
    # depth bounds bracket the unit ball; the bounds box is about the ball
    k = c.scale_to_input
    dist = back_cams.centers.norm(dim=-1)
    near, far = c.near * k, c.far * k
    assert (near < dist - 0.5).all() and (far > dist + 0.5).all() and (near > 0.9 * (dist - 1) - 1e-9).all()
    half = (c.bounds[1] - c.bounds[0]) * k / 2  # a box about the ball: half-sides near 1 (rotated frame)
    assert (half > 0.8).all() and (half < 1.1).all()
    assert torch.allclose(c.points_to_input(c.bounds.double().mean(0, keepdim=True)), torch.zeros(1, 3, dtype=torch.float64), atol=0.15)
    assert {k: len(v) for k, v in c.splits.items()} == {"all": 10, "train": 8, "test": 2}


def _undistort_points(xd, yd, d, iters=50):
    x, y = xd.clone(), yd.clone()
    for _ in range(iters):  # fixed point: x = xd - (distort(x) - x)
        dx, dy = distort(x, y, d)
        x, y = x + (xd - dx), y + (yd - dy)
    return x, y


@pytest.mark.parametrize("model,params,dist", [
    ("SIMPLE_PINHOLE", [80.0, 48.0, 36.0], [0] * 6),
    ("PINHOLE", [80.0, 84.0, 47.0, 37.0], [0] * 6),
    ("SIMPLE_RADIAL", [80.0, 48.0, 36.0, -0.15], [-0.15, 0, 0, 0, 0, 0]),
    ("RADIAL", [80.0, 48.0, 36.0, 0.1, -0.05], [0.1, -0.05, 0, 0, 0, 0]),
    ("OPENCV", [80.0, 84.0, 47.0, 37.0, -0.12, 0.03, 0.004, -0.003], [-0.12, 0.03, 0, 0, 0.004, -0.003]),
])
def test_colmap_camera_models_undistort(tmp_path, model, params, dist):
    w, h = 96, 72
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx, fy, cx, cy = params[0], params[0], params[1], params[2]
    else:
        fx, fy, cx, cy = params[:4]
    pattern = lambda x, y: 0.5 + 0.4 * torch.sin(4 * x + 1) * torch.cos(3 * y)  # noqa: E731
    v, u = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    u, v = u.double(), v.double()
    d = torch.tensor(dist, dtype=torch.float64)
    x, y = _undistort_points((u - cx) / fx, (v - cy) / fy, d)
    img = pattern(x, y)[..., None].expand(h, w, 3)
    write_image(tmp_path / "images" / "a.png", (img.numpy() * 65535).astype(np.uint16)[..., 0])
    c2w = look_at(torch.tensor([[0.0, 0, -3]]), torch.zeros(3), torch.tensor([0, -1.0, 0]))[0]
    w2c = torch.linalg.inv(c2w).numpy()
    pts = np.random.default_rng(0).uniform(-0.5, 0.5, (50, 3))
    m = Model({1: Camera(1, model, w, h, np.array(params))},
              [Image(1, rotmat_to_qvec(w2c[:3, :3]), w2c[:3, 3], 1, "a.png", np.zeros((0, 2)), np.zeros(0, np.int64))],
              Points(np.arange(50), pts, np.zeros((50, 3), np.uint8), np.zeros(50), [np.zeros((0, 2), np.int64)] * 50),
              None, None)
    write_model(m, tmp_path / "sparse", ".txt")
    s = load_scene(tmp_path)
    assert s.cameras.K[0].tolist() == [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
    truth = pattern((u - cx) / fx, (v - cy) / fy)  # the pinhole image of the pattern
    xd, yd = distort((u - cx) / fx, (v - cy) / fy, d)
    valid = ((fx * xd + cx > 1) & (fx * xd + cx < w - 1) & (fy * yd + cy > 1) & (fy * yd + cy < h - 1))
    err = (s.images[0, ..., 0].double() - truth).abs()[valid]
    assert err.max() < 0.02 and valid.float().mean() > 0.8
    if any(dist):  # without undistortion the image would be clearly wrong
        assert (img[..., 0] - truth).abs()[valid].max() > 20 * err.max()


# ---------------------------------------------------------------------- Blender extension (procedural scenes)
def test_blender_extension_sphere(tmp_path):
    """An analytic sphere rendered with depth, normals, labels and masks reads back consistently."""
    w, h, r, depth_scale = 40, 30, 0.6, 1e-4
    eye = torch.tensor([[3.0, 0.5, 0.3], [-2.5, 1.5, 0.8], [0.4, -3.0, -0.5]], dtype=torch.float64)
    c2w = look_at(eye, torch.zeros(3), torch.tensor([0, 0, 1.0]))
    cams = Cameras(torch.full((3,), 45.0), torch.full((3,), 47.0), torch.full((3,), 20.5), torch.full((3,), 14.0),
                   c2w.double(), w, h)
    o, dirs = cams.image_rays(normalize=False)  # [N, H, W, 3], camera z = 1
    a, b, c = (dirs * dirs).sum(-1), 2 * (o * dirs).sum(-1), (o * o).sum(-1) - r * r
    disc = b * b - 4 * a * c
    hit = disc > 0
    z = torch.where(hit, (-b - disc.clamp_min(0).sqrt()) / (2 * a), torch.zeros_like(a))  # z-depth
    normal = torch.where(hit[..., None], (o + z[..., None] * dirs) / r, torch.zeros_like(o))
    frames = []
    for i in range(3):
        rgba = torch.cat([torch.full((h, w, 3), 0.25, dtype=torch.float64), hit[i, ..., None].double()], -1)
        write_image(tmp_path / f"rgb_{i}.png", rgba.numpy())
        write_image(tmp_path / f"depth_{i}.png", np.rint(z[i].numpy() / depth_scale).astype(np.uint16))
        write_image(tmp_path / f"normal_{i}.png", np.rint((normal[i].numpy() + 1) * 127.5).astype(np.uint8))
        write_image(tmp_path / f"label_{i}.png", (hit[i].numpy() * 7).astype(np.uint8))
        frames.append({"file_path": f"rgb_{i}", "transform_matrix": (c2w[i] @ torch.diag(torch.tensor(
            [1.0, -1, -1, 1], dtype=torch.float64))).tolist(), "depth_file_path": f"depth_{i}.png",
            "normal_file_path": f"normal_{i}.png", "label_file_path": f"label_{i}.png"})
    (tmp_path / "mesh.ply").write_text("ply\n")
    top = {"fl_x": 45.0, "fl_y": 47.0, "cx": 20.5, "cy": 14.0, "w": w, "h": h, "near": 1.0, "far": 5.0,
           "aabb": [[-1, -1, -1], [1, 1, 1]], "rig": "object", "mesh_path": "mesh.ply", "depth_scale": depth_scale}
    write_json(tmp_path / "transforms_train.json", {**top, "frames": frames[:2]})
    write_json(tmp_path / "transforms_test.json", {**top, "frames": frames[2:]})
    assert detect_format(tmp_path) == "blender"
    s = load_scene(tmp_path)
    assert torch.allclose(s.cameras.c2w, c2w.double(), atol=1e-9) and torch.allclose(s.cameras.K, cams.K)
    assert s.splits == {"all": [0, 1, 2], "train": [0, 1], "test": [2]}
    assert s.mesh_path == tmp_path / "mesh.ply" and float(s.near[0]) == 1 and float(s.far[0]) == 5
    assert torch.equal(s.masks, hit) and torch.equal(s.labels, hit.long() * 7)
    # depth lifts onto the sphere, and the normals agree with the lifted points
    pts = s.cameras.unproject(s.cameras.pixel_centers().expand(3, h, w, 2), s.depths.double())
    assert ((pts[hit].norm(dim=-1) - r).abs() < 1e-3).all()
    assert ((s.normals[hit].double() - pts[hit] / r).norm(dim=-1) < 0.02).all()
    assert (s.depths[~hit] == 0).all() and (s.normals[~hit] == 0).all()
    half = load_scene(tmp_path, options=ReadOptions(downscale=2))
    assert torch.equal(half.depths, s.depths[:, 1::2, 1::2])  # nearest: the pixel holding the new centre
    assert torch.allclose(half.cameras.fx, s.cameras.fx / 2)
    assert set(half.labels.unique().tolist()) <= {0, 7}


# ---------------------------------------------------------------------- held-out views stay held out
def _held_out_scenes(tmp_path):
    """One scene per reader: the shared real scenes, plus written MVSNet (49 views, as DTU) and COLMAP ones."""
    out = [scene(rel, downscale=8) for rel in SCENES]
    dtu = out[-1]
    out.append(load_scene(write_mvsnet(dtu, tmp_path / "mvs", layout="test", scan="scan37")))
    write_model(colmap_from_scene(dtu), tmp_path / "colmap" / "sparse" / "0", ".bin")
    for i in range(len(dtu)):
        write_image(tmp_path / "colmap" / "images" / f"view_{i:03d}.png", dtu.images[i].numpy())
    out.append(load_scene(tmp_path / "colmap"))
    return out


def test_every_reader_holds_out_the_protocols_views(tmp_path):
    """Every reader gives a test split = the evaluation protocol's held-out views, disjoint from the
    training views that `--views all` meshes, finetune tunes on and the default sources come from."""
    from omnirecon.engine.protocols import protocol_for, targets_and_pool
    from omnirecon.engine.views import check_views, default_views

    formats = set()
    for s in _held_out_scenes(tmp_path):
        formats.add(s.format)
        test, train = set(s.splits.get("test", [])), set(s.splits["train"])
        assert test and not test & train, (s.path, s.splits)
        targets, pool = targets_and_pool(protocol_for(s.path, s.format), s)
        assert set(targets) <= test and not set(pool) & test, (s.path, targets)
        assert not set(check_views(["all"], len(s), s.path, s)) & test
        assert not set(default_views(s, 3)) & test
    assert formats == {"blender", "ngp", "llff", "dtu_neus", "dtu_mvsnet", "colmap"}
