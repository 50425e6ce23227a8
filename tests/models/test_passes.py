"""The output-changing options of the two-pass models (IBRNet, Omni-Recon): ``fine_pass`` and
``surface_samples``, keyword arguments of ``render_rays`` and ``render_view`` (not fast-path switches)."""

import pytest
import torch

from omnirecon.models import fast
from omnirecon.rays import Rays
from tests.models.test_fast_paths import MODELS, render, scene


@pytest.mark.parametrize("name", ["ibrnet", "omnirecon"])
def test_surface_samples_fine_pass(name):
    """surface_samples: the fine pass evaluates exactly N samples, drawn where the coarse weights are
    (inside the coarse depth range, sorted); training (jitter) keeps coarse + importance samples."""
    from omnirecon.models.sampler import fine_depths

    torch.manual_seed(0)
    z = torch.linspace(2.0, 4.0, 12).expand(5, 12).contiguous()
    w = torch.zeros(5, 12)
    w[:, 6] = 1.0  # all the mass in one coarse interval
    zf = fine_depths(z, w, 4, surface_samples=6)
    assert zf.shape == (5, 6) and (zf.diff(dim=-1) >= 0).all()
    mid = 0.5 * (z[:, 1:] + z[:, :-1])
    inner = zf[:, 1:-1]  # the deterministic CDF samples away from the two ends sit in that interval
    assert ((inner >= mid[:, 5:6] - 1e-6) & (inner <= mid[:, 6:7] + 1e-6)).all()
    assert fine_depths(z, w, 4, jitter=True, surface_samples=6).shape == (5, 16)
    assert fine_depths(z, w, 4).shape == (5, 16)
    model = MODELS[name]().eval()
    src, target = scene()
    out = render(model, src, target)
    surf = model.render_view(model.encode(src), target, chunk=100, surface_samples=6)
    assert torch.isfinite(surf["rgb"]).all() and surf["rgb"].shape == (target.height, target.width, 3)
    assert not torch.equal(surf["rgb"], out["rgb"])


@pytest.mark.parametrize("name", ["ibrnet", "omnirecon"])
def test_fine_pass_off_renders_the_coarse_pass(name):
    """fine_pass=False outside training: the main outputs are the reference's coarse pass exactly;
    training (jitter) still runs both passes; the process-wide switches are untouched."""
    torch.manual_seed(0)
    model = MODELS[name]().eval()
    src, target = scene()
    with fast.reference():
        ref = render(model, src, target)
        with torch.no_grad():
            out = model.render_view(model.encode(src), target, chunk=100, fine_pass=False)
    torch.testing.assert_close(out["rgb"], ref["rgb_coarse"], atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(out["depth"], ref.get("depth_coarse", ref["depth"]) if name == "omnirecon"
                               else ref["depth_coarse"], atol=1e-6, rtol=1e-6)
    rays = Rays.from_image(target)[:16]
    with torch.no_grad():
        feats = model.encode(src)
        trained = model.render_rays(feats, rays, jitter=True, fine_pass=False)
        coarse = model.render_rays(feats, rays, fine_pass=False)
    assert trained["rgb"].shape == (16, 3) and not torch.equal(trained["rgb"], trained["rgb_coarse"])
    torch.testing.assert_close(coarse["rgb"], coarse["rgb_coarse"], atol=0, rtol=0)
    assert fast.FAST == fast.FastPaths() or fast.FAST == fast.from_env(None)


@pytest.mark.parametrize("name", ["gpnr"])
def test_one_pass_models_ignore_pass_options(name):
    """A one-pass model renders its only pass whatever fine_pass and surface_samples say."""
    torch.manual_seed(0)
    model = MODELS[name]().eval()
    src, target = scene()
    with torch.no_grad():
        feats = model.encode(src)
    a = model.render_view(feats, target, chunk=100)
    b = model.render_view(feats, target, chunk=100, fine_pass=False, surface_samples=4)
    assert not model.capabilities.passes and torch.equal(a["rgb"], b["rgb"])


def test_render_fine_pass_config_sets_the_default_pass():
    """Omni-Recon's ``render_fine_pass = False`` (the shipped omnirecon-tiny's): ``render_view`` without
    ``fine_pass`` renders the coarse pass, ``fine_pass=True`` still renders the fine one, training both."""
    import dataclasses

    torch.manual_seed(0)
    model = MODELS["omnirecon"]().eval()
    src, target = scene()
    with torch.no_grad():
        feats = model.encode(src)
        fine = model.render_view(feats, target, chunk=100)
        model.cfg = dataclasses.replace(model.cfg, render_fine_pass=False)
        default = model.render_view(feats, target, chunk=100)
        asked = model.render_view(feats, target, chunk=100, fine_pass=True)
        rays = Rays.from_image(target)[:16]
        trained = model.render_rays(feats, rays, jitter=True)
    torch.testing.assert_close(default["rgb"], fine["rgb_coarse"], atol=1e-6, rtol=1e-6)
    assert not torch.equal(default["rgb"], fine["rgb"])
    torch.testing.assert_close(asked["rgb"], fine["rgb"], atol=1e-6, rtol=1e-6)
    assert not torch.equal(trained["rgb"], trained["rgb_coarse"])


def test_ibrnet_render_samples_stand_for_the_trained():
    """IBRNet's render_coarse_samples / render_fine_samples: at the trained counts the render is unchanged;
    fewer samples render finite images that differ; each fine-pass sample is flagged coarse or importance by
    ``fine_depths(origin=True)``; training (jitter) and the code of trained positions ignore them."""
    import dataclasses

    from omnirecon.models.ibrnet import position_code, sample_index_code
    from omnirecon.models.sampler import fine_depths

    torch.manual_seed(0)
    model = MODELS["ibrnet"]().eval()
    cfg = model.cfg
    src, target = scene()
    out = render(model, src, target)
    model.cfg = dataclasses.replace(cfg, render_coarse_samples=cfg.coarse_samples, render_fine_samples=cfg.fine_samples)
    torch.testing.assert_close(render(model, src, target)["rgb"], out["rgb"], atol=0, rtol=0)
    model.cfg = dataclasses.replace(cfg, render_coarse_samples=cfg.coarse_samples // 2,
                                    render_fine_samples=max(cfg.fine_samples // 2, 1))
    fewer = render(model, src, target)
    assert torch.isfinite(fewer["rgb"]).all() and not torch.equal(fewer["rgb"], out["rgb"])
    rays = Rays.from_image(target)[:8]
    with torch.no_grad():
        trained = model.render_rays(model.encode(src), rays, jitter=True)
    assert trained["z_coarse"].shape[-1] == cfg.coarse_samples
    z = torch.linspace(2.0, 4.0, 6).expand(3, 6).contiguous()
    zf, coarse = fine_depths(z, torch.rand(3, 6), 4, origin=True)
    assert zf.shape == coarse.shape == (3, 10) and (coarse.sum(-1) == 6).all()
    torch.testing.assert_close(position_code(torch.arange(9.0), 16), sample_index_code(9, 16), atol=0, rtol=0)
