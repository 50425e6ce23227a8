import math

import pytest
import torch

from omnirecon.cameras import (
    Cameras,
    apply_transform,
    canonical_transform,
    check_poses,
    closest_point_to_axes,
    look_at,
    nearest_views,
    opengl_to_opencv,
    orthonormalize,
    plucker,
    rigid_inverse,
    sample_views,
)
from omnirecon.errors import InputError


@pytest.fixture(autouse=True)
def float64_default():
    """These tests compare to 1e-9: run them in float64 without leaking the setting."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


def random_rotation(g):
    q = torch.randn(4, generator=g)
    q = q / q.norm()
    w, x, y, z = q
    return torch.tensor([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def random_rigid(g):
    T = torch.eye(4)
    T[:3, :3] = random_rotation(g)
    T[:3, 3] = torch.randn(3, generator=g) * 3
    return T


def ring(n=8, radius=4.0, w=64, h=48, f=60.0):
    ang = torch.linspace(0, 2 * math.pi, n + 1)[:-1]
    eye = torch.stack([radius * torch.cos(ang), radius * torch.sin(ang), 1.0 + 0 * ang], -1)
    c2w = look_at(eye, torch.zeros(3), torch.tensor([0, 0, 1.0]))
    return Cameras(torch.full((n,), f), torch.full((n,), f * 1.1), torch.full((n,), w / 2 + 1.3),
                   torch.full((n,), h / 2 - 0.7), c2w, w, h)


def test_look_at_is_rigid_and_looks_at_target():
    cams = ring()
    check_poses(cams.c2w)
    assert torch.allclose(torch.linalg.det(cams.R), torch.ones(len(cams)))
    proj = cams.project(torch.zeros(1, 3))
    # the origin projects onto the principal point of every camera
    assert torch.allclose(proj.uv[:, 0], torch.stack([cams.cx, cams.cy], -1), atol=1e-9)
    # world +z (up) appears upwards in the image: v decreases
    up = cams.project(torch.tensor([[0, 0, 0.5]])).uv[:, 0, 1]
    assert (up < cams.cy).all()


def test_project_unproject_round_trip():
    g = torch.Generator().manual_seed(0)
    cams = ring()
    uv = torch.rand(len(cams), 100, 2, generator=g) * torch.tensor([cams.width, cams.height])
    z = 1 + 5 * torch.rand(len(cams), 100, generator=g)
    pts = cams.unproject(uv, z)  # [N, P, 3]
    proj = cams.project(pts)
    assert torch.allclose(proj.uv, uv, atol=1e-9)
    assert torch.allclose(proj.depth, z, atol=1e-9)
    assert proj.in_image.all() and proj.in_front.all()


def test_pixel_centre_convention():
    cams = ring(n=1, w=4, h=2)
    cams = Cameras(cams.fx, cams.fy, torch.tensor([2.0]), torch.tensor([1.0]), cams.c2w, 4, 2)
    centers = cams.pixel_centers()
    assert centers[0, 0].tolist() == [0.5, 0.5] and centers[1, 3].tolist() == [3.5, 1.5]
    # the ray through (cx, cy) is the optical axis
    o, d = cams.rays(torch.tensor([[[2.0, 1.0]]]))
    assert torch.allclose(d[0, 0], cams.forward[0])


def test_behind_camera_is_masked():
    cams = ring(n=2)
    behind = cams.centers[0] - 2 * cams.forward[0]
    proj = cams.project(behind[None])
    assert not proj.in_front[0, 0] and not proj.in_image[0, 0]


def test_plucker_invariants():
    g = torch.Generator().manual_seed(1)
    o = torch.randn(50, 3, generator=g)
    d = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=-1)
    p = plucker(o, d)
    assert torch.allclose((p[:, :3] * p[:, 3:]).sum(-1), torch.zeros(50), atol=1e-12)  # d . m = 0
    # moving the origin along the ray leaves the coordinates unchanged
    assert torch.allclose(plucker(o + 2.5 * d, d), p, atol=1e-12)
    # d and -d: the moment flips with the direction
    assert torch.allclose(plucker(o, -d), -p, atol=1e-12)


def test_canonical_transform_is_rigid_and_maps_ray_to_z_axis():
    g = torch.Generator().manual_seed(2)
    cams = ring()
    uv = torch.rand(len(cams), 30, 2, generator=g) * 40
    o, d = cams.rays(uv)
    up = cams.R[:, None, :, 1].expand_as(d)
    T = canonical_transform(o, d, up)  # [N, 30, 4, 4]
    R = T[..., :3, :3]
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3).expand_as(R), atol=1e-10)
    assert torch.allclose(torch.linalg.det(R), torch.ones(R.shape[:-2]), atol=1e-10)
    assert torch.allclose((R @ d[..., None])[..., 0], torch.tensor([0, 0, 1.0]).expand_as(d), atol=1e-10)
    origin = apply_transform(T, o[..., None, :])[..., 0, :]
    assert torch.allclose(origin, torch.zeros_like(origin), atol=1e-10)
    # the 'up' component maps to +y: its x is zero and y positive
    u = (R @ up[..., None])[..., 0]
    assert torch.allclose(u[..., 0], torch.zeros_like(u[..., 0]), atol=1e-10) and (u[..., 1] > 0).all()


def test_canonical_inputs_invariant_to_world_rigid_transform():
    g = torch.Generator().manual_seed(3)
    cams = ring(n=6)
    target, sources = cams[[0]], cams[1:]
    uv = torch.rand(1, 20, 2, generator=g) * 40
    points_t = torch.linspace(1, 6, 7)

    def canonical_inputs(target, sources):
        o, d = target.rays(uv)  # [1, 20, 3]
        T = canonical_transform(o[0], d[0], target.R[0, :, 1])  # [20, 4, 4]
        pts = o[0, :, None] + d[0, :, None] * points_t[:, None]  # [20, 7, 3]
        pts_c = apply_transform(T, pts)
        centres_c = apply_transform(T, sources.centers.expand(20, -1, -1))  # [20, S, 3]
        src_o, src_d = sources.centers[:, None].expand(-1, 7 * 20, -1), pts.reshape(1, -1, 3) - sources.centers[:, None]
        ray_c = plucker(
            apply_transform(T.repeat_interleave(1, 0), src_o.reshape(len(sources), 20, 7, 3).permute(1, 0, 2, 3).reshape(20, -1, 3)),
            (T[:, None, :3, :3] @ src_d.reshape(len(sources), 20, 7, 3).permute(1, 0, 2, 3).reshape(20, -1, 3)[..., None])[..., 0],
        )
        return pts_c, centres_c, ray_c

    a = canonical_inputs(target, sources)
    M = random_rigid(g)
    b = canonical_inputs(target.transformed(M), sources.transformed(M))
    for x, y in zip(a, b):
        assert torch.allclose(x, y, atol=1e-9)
    # points on the target ray become (0, 0, t)
    assert torch.allclose(a[0][..., :2], torch.zeros_like(a[0][..., :2]), atol=1e-9)


def test_opengl_to_opencv_flips_y_and_z():
    c2w_gl = torch.eye(4)[None]
    c2w = opengl_to_opencv(c2w_gl)
    assert torch.allclose(c2w[0, :3, 2], torch.tensor([0, 0, -1.0]))  # looks along world -z
    assert torch.linalg.det(c2w[0, :3, :3]) > 0


def test_check_poses_rejects_bad():
    good = ring().c2w
    check_poses(good)
    bad = good.clone(); bad[0, 0, 0] = float("nan")
    with pytest.raises(InputError, match="NaN"):
        check_poses(bad, "poses.json")
    refl = good.clone(); refl[1, :3, 0] *= -1
    with pytest.raises(InputError, match="det R = -1"):
        check_poses(refl)
    scaled = good.clone(); scaled[2, :3, :3] *= 2
    with pytest.raises(InputError, match="not rigid"):
        check_poses(scaled)
    noisy = good + 1e-5 * torch.randn_like(good)
    check_poses(orthonormalize(noisy), tol=1e-9)


def test_rigid_inverse():
    g = torch.Generator().manual_seed(4)
    T = torch.stack([random_rigid(g) for _ in range(5)])
    assert torch.allclose(rigid_inverse(T) @ T, torch.eye(4).expand(5, 4, 4), atol=1e-12)


def test_view_selection():
    cams = ring(n=12)
    idx = nearest_views(cams[[0]], cams, k=3, exclude=torch.tensor([0]))
    assert sorted(idx[0].tolist()[:2]) == [1, 11] and 0 not in idx[0].tolist()
    by_angle = nearest_views(cams[[0]], cams, k=3, by="angle", exclude=torch.tensor([0]))
    assert sorted(by_angle[0].tolist()[:2]) == [1, 11]
    g = torch.Generator().manual_seed(0)
    draws = {tuple(sorted(sample_views(cams[[0]], cams, 2, 4, g, exclude=torch.tensor([0]))[0].tolist()))
             for _ in range(50)}
    assert all(set(d) <= {1, 2, 10, 11} for d in draws) and len(draws) > 1
    assert torch.allclose(closest_point_to_axes(cams), torch.zeros(3), atol=1e-9)


def test_rescale_keeps_rays():
    cams = ring()
    half = cams.rescaled(0.5)
    # the top-left corner of the image is the same ray at both resolutions
    o1, d1 = cams.rays(torch.zeros(len(cams), 1, 2))
    o2, d2 = half.rays(torch.zeros(len(cams), 1, 2))
    assert torch.allclose(d1, d2)


def test_scene_normalized_round_trip():
    from omnirecon.data.scene import Scene

    cams = ring(n=4, radius=40.0)
    n = len(cams)
    scene = Scene(images=torch.zeros(n, cams.height, cams.width, 3), cameras=cams,
                  near=torch.full((n,), 20.0), far=torch.full((n,), 60.0),
                  bounds=torch.tensor([[-10.0, -10, -5], [10, 10, 15]]), splits={},
                  depths=torch.full((n, cams.height, cams.width), 30.0))
    norm = scene.normalized()
    assert torch.allclose(norm.bounds.mean(0), torch.zeros(3), atol=1e-9)
    assert abs(float((norm.bounds[1] - norm.bounds[0]).norm()) - 2) < 1e-9
    # a world point, projected in both frames, lands on the same pixel
    p = torch.tensor([[1.0, 2.0, 3.0]])
    p_norm = (p - scene.bounds.mean(0)) * (2 / float((scene.bounds[1] - scene.bounds[0]).norm()))
    assert torch.allclose(scene.cameras.project(p).uv, norm.cameras.project(p_norm).uv, atol=1e-9)
    assert torch.allclose(norm.points_to_input(p_norm), p, atol=1e-9)
    check_poses(norm.cameras.c2w)


def test_atomic_writes_get_normal_permissions(tmp_path):
    import os

    from omnirecon.data.io import write_json

    write_json(tmp_path / "a.json", {"x": 1})
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o666 & ~umask
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
