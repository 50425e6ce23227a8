
import pytest
import torch

from omnirecon.cameras import Cameras, look_at
from omnirecon.models.gpnr import GPNR, PRESETS, GPNRConfig
from omnirecon.rays import Rays, Sources
from tests.test_cameras import random_rigid


def rig(n=5, w=24, h=20, dtype=torch.float64):
    ang = torch.linspace(-0.6, 0.6, n, dtype=dtype)
    eye = torch.stack([3 * torch.sin(ang), -3 * torch.cos(ang), 0.4 + 0.1 * ang], -1)
    c2w = look_at(eye, torch.zeros(3, dtype=dtype), torch.tensor([0, 0, 1.0], dtype=dtype))
    f = torch.full((n,), 22.0, dtype=dtype)
    return Cameras(f, f, f * 0 + w / 2, f * 0 + h / 2, c2w, w, h)


def small_cfg(**kw):
    base = dict(PRESETS["gpnr-tiny"].__dict__)
    base.update(num_samples=8, dim=32, mlp_dim=32, layers=(1, 1, 1), patch_channels=8, patch_size=5)
    base.update(kw)
    return GPNRConfig(**base)


def setup(cfg, seed=0):
    torch.manual_seed(seed)
    model = GPNR(cfg).double().eval()
    cams = rig()
    images = torch.rand(len(cams) - 1, cams.height, cams.width, 3, dtype=torch.float64)
    target = cams[[len(cams) // 2]]
    src_idx = [i for i in range(len(cams)) if i != len(cams) // 2]
    return model, cams[src_idx], images, target


@pytest.mark.parametrize("ray_param", ["plucker", "lightslab", "twosphere"])
def test_invariant_to_rigid_world_transform(ray_param):
    model, srcs, images, target = setup(small_cfg(ray_param=ray_param, scene_radius=1e9 if ray_param == "twosphere" else 1.0))
    uv = torch.rand(30, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 20
    out = []
    for T in (torch.eye(4, dtype=torch.float64), random_rigid(torch.Generator().manual_seed(2))):
        s, t = srcs.transformed(T), target.transformed(T)
        feats = model.encode(Sources(images, s, 2.0, 4.0))
        rays = Rays.from_pixels(t, torch.zeros(30, dtype=torch.long), uv)
        out.append(model.render_rays(feats, rays))
    if ray_param == "twosphere":  # the sphere is fixed in the world: only test it runs
        return
    for k in ("rgb", "rgb_aux", "depth"):
        assert torch.allclose(out[0][k], out[1][k], atol=1e-9), k


def test_invariant_to_source_permutation():
    model, srcs, images, target = setup(small_cfg())
    uv = torch.rand(30, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 20
    rays = Rays.from_pixels(target, torch.zeros(30, dtype=torch.long), uv)
    a = model.render_rays(model.encode(Sources(images, srcs, 2.0, 4.0)), rays)
    perm = torch.tensor([2, 0, 3, 1])
    b = model.render_rays(model.encode(Sources(images[perm], srcs[perm], 2.0, 4.0)), rays)
    for k in ("rgb", "rgb_aux", "depth"):
        assert torch.allclose(a[k], b[k], atol=1e-9), k
    assert torch.allclose(a["blend"][:, perm], b["blend"], atol=1e-9)


def test_world_frame_ablation_is_not_invariant():
    model, srcs, images, target = setup(small_cfg(canonical_rays=False, canonical_coords=False))
    uv = torch.rand(10, 2, dtype=torch.float64) * 20
    outs = []
    for T in (torch.eye(4, dtype=torch.float64), random_rigid(torch.Generator().manual_seed(2))):
        feats = model.encode(Sources(images, srcs.transformed(T), 2.0, 4.0))
        outs.append(model.render_rays(feats, Rays.from_pixels(target.transformed(T), torch.zeros(10, dtype=torch.long), uv))["rgb"])
    assert not torch.allclose(outs[0], outs[1], atol=1e-6)


def test_outputs_are_convex_blends():
    model, srcs, images, target = setup(small_cfg())
    feats = model.encode(Sources(images, srcs, 2.0, 4.0))
    out = model.render_view(feats, target, chunk=100)
    assert out["rgb"].shape == (20, 24, 3) and out["rgb_aux"].shape == (20, 24, 3)
    blend = out["blend"].reshape(-1, 4)
    ok = out["valid"].reshape(-1)
    assert torch.allclose(blend[ok].sum(-1), torch.ones(int(ok.sum()), dtype=torch.float64))
    assert (out["rgb_aux"] >= 0).all() and (out["rgb_aux"] <= 1).all()
    assert (out["depth"][out["valid"]] >= 2.0 - 1e-9).all() and (out["depth"][out["valid"]] <= 4.0 + 1e-9).all()


def test_mask_invalid_ignores_points_outside_images():
    model, srcs, images, target = setup(small_cfg())
    feats = model.encode(Sources(images, srcs, 2.0, 4.0))
    rays = Rays.from_pixels(target, torch.zeros(5, dtype=torch.long), torch.rand(5, 2, dtype=torch.float64) * 20)
    base = model.render_rays(feats, rays)
    # changing pixels of a source image that no sample projects to leaves the output unchanged
    proj = srcs.project((rays.origins[:, None] + rays.directions[:, None] * torch.linspace(2, 6, 50, dtype=torch.float64)[:, None]).reshape(-1, 3))
    used = torch.zeros(len(srcs), 20, 24, dtype=torch.bool)
    for k in range(len(srcs)):
        uv = proj.uv[k][proj.in_image[k]]
        r, c = uv[:, 1].long().clamp(0, 19), uv[:, 0].long().clamp(0, 23)
        for dr in range(-4, 5):
            for dc in range(-4, 5):
                used[k, (r + dr).clamp(0, 19), (c + dc).clamp(0, 23)] = True
    images2 = torch.where(used[..., None], images, torch.rand_like(images))
    out = model.render_rays(model.encode(Sources(images2, srcs, 2.0, 4.0)), rays)
    assert torch.allclose(base["rgb"], out["rgb"], atol=1e-9)
