import torch

from omnirecon.models.ibrnet import PRESETS, IBRNet, IBRNetConfig, sample_index_code
from omnirecon.rays import Rays, Sources
from tests.models.test_gpnr import rig


def tiny(**kw):
    cfg = dict(PRESETS["ibrnet-tiny"].__dict__)
    cfg.update(coarse_samples=12, fine_samples=6, channels=(8, 8, 8), feature_dim=8)
    cfg.update(kw)
    return IBRNetConfig(**cfg)


def test_shapes_weights_and_depth_range():
    torch.manual_seed(0)
    model = IBRNet(tiny()).eval()
    cams = rig(dtype=torch.float32)
    images = torch.rand(4, cams.height, cams.width, 3)
    feats = model.encode(Sources(images, cams[[0, 1, 3, 4]], 2.0, 4.0))
    assert feats.maps.shape == (4, 16, cams.height // 2, cams.width // 2)
    out = model.render_view(feats, cams[[2]], chunk=128)
    assert out["rgb"].shape == (cams.height, cams.width, 3) and out["rgb_coarse"].shape == out["rgb"].shape
    assert (out["rgb"] >= 0).all() and (out["rgb"] <= 1 + 1e-5).all()
    assert (out["acc"] <= 1 + 1e-5).all()
    rays = Rays.from_image(cams[[2]])[:64]
    r = model.render_rays(feats, rays, jitter=True)
    assert r["rgb"].shape == (64, 3) and torch.isfinite(r["rgb"]).all()


def test_permutation_invariant():
    torch.manual_seed(0)
    model = IBRNet(tiny()).double().eval()
    cams = rig()
    images = torch.rand(4, cams.height, cams.width, 3, dtype=torch.float64)
    rays = Rays.from_image(cams[[2]])[:50]
    a = model.render_rays(model.encode(Sources(images, cams[[0, 1, 3, 4]], 2.0, 4.0)), rays)
    p = torch.tensor([3, 1, 0, 2])
    b = model.render_rays(model.encode(Sources(images[p], cams[[0, 1, 3, 4]][p], 2.0, 4.0)), rays)
    assert torch.allclose(a["rgb"], b["rgb"], atol=1e-9)


def test_position_code_any_length():
    assert sample_index_code(7, 16).shape == (7, 16)
    assert torch.allclose(sample_index_code(100, 16)[:7], sample_index_code(7, 16))
