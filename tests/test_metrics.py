"""Metrics: PSNR/SSIM against closed forms and scikit-image, ST-LPIPS ordering, LPIPS never downloading."""

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from omnirecon import metrics


def textured(h=64, w=64, seed=0) -> torch.Tensor:
    """A smooth, structured test image in [0, 1] (blurred noise plus a gradient). ``# [H, W, 3]``"""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    img = gaussian_filter(rng.uniform(size=(h, w, 3)), sigma=(2, 2, 0))
    img = (img - img.min()) / (img.max() - img.min())
    img = 0.7 * img + 0.3 * np.linspace(0, 1, w)[None, :, None]
    return torch.from_numpy(img.astype(np.float32))


def noisy(img: torch.Tensor, sigma: float, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (img + sigma * torch.randn(img.shape, generator=g)).clamp(0, 1)


def test_identical_images():
    a = textured()
    assert metrics.psnr(a, a) == math.inf  # documented: no cap
    assert metrics.ssim(a, a) == pytest.approx(1.0, abs=1e-6)


def test_psnr_of_known_mse_and_mask():
    gt = torch.full((16, 20, 3), 0.5, dtype=torch.float64)
    pred = gt + 0.1  # MSE = 0.01 -> 20 dB
    assert metrics.psnr(pred, gt) == pytest.approx(20.0, abs=1e-9)
    pred = gt.clone()
    pred[:, :10] += 0.01  # left half off by 0.01 (40 dB alone), right half exact
    mask = torch.zeros(16, 20, dtype=torch.bool)
    mask[:, :10] = True
    assert metrics.psnr(pred, gt, mask) == pytest.approx(40.0, abs=1e-6)
    assert metrics.psnr(pred, gt, ~mask) == math.inf
    assert metrics.psnr(pred, gt) == pytest.approx(40.0 + 10 * math.log10(2), abs=1e-6)  # half the MSE
    assert math.isnan(metrics.psnr(pred, gt, torch.zeros(16, 20, dtype=torch.bool)))
    # NumPy input works the same
    assert metrics.psnr(pred.numpy(), gt.numpy()) == pytest.approx(metrics.psnr(pred, gt))


def test_ssim_matches_skimage_gaussian():
    gt = textured(96, 80)
    pred = noisy(gt, 0.05)
    ours = metrics.ssim(pred, gt)
    ref = structural_similarity(pred.numpy().astype(np.float64), gt.numpy().astype(np.float64), gaussian_weights=True,
                                sigma=1.5, use_sample_covariance=False, channel_axis=-1, data_range=1.0)
    assert ours == pytest.approx(ref, abs=1e-4)
    assert 0.3 < ours < 0.99


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="H, W, 3"):
        metrics.psnr(torch.zeros(8, 8), torch.zeros(8, 8))
    with pytest.raises(ValueError, match="differ"):
        metrics.ssim(torch.zeros(16, 16, 3), torch.zeros(16, 17, 3))
    with pytest.raises(ValueError, match="at least 11"):
        metrics.ssim(torch.zeros(8, 16, 3), torch.zeros(8, 16, 3))


def test_st_lpips_orders_distortions():
    if metrics.unavailable("st_lpips"):
        pytest.skip(metrics.unavailable("st_lpips"))
    a = textured(64, 64, seed=0)
    same = metrics.st_lpips(a, a)
    light = metrics.st_lpips(noisy(a, 0.02), a)
    unrelated = metrics.st_lpips(textured(64, 64, seed=5).flip(1), a)
    assert same == pytest.approx(0.0, abs=1e-6)
    assert 0 < light < unrelated
    # Shift tolerance: a 1-pixel shift costs less than light noise does in PSNR terms, and far less
    # than an unrelated image.
    shifted = torch.roll(a, 1, dims=1)
    assert metrics.st_lpips(shifted, a) < unrelated / 4


def test_perceptual_metrics_do_not_leave_stubs_behind():
    import importlib.util
    import sys

    metrics.unavailable("st_lpips")
    for name in ("IPython", "torchsummary", "torchvision"):
        if importlib.util.find_spec(name) is None:
            assert name not in sys.modules


def test_lpips_never_downloads(monkeypatch, tmp_path):
    """Without cached backbone weights standard LPIPS is reported unavailable, not fetched."""
    monkeypatch.setattr(metrics, "_REASONS", {})
    monkeypatch.setattr(metrics, "_NETS", {})
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))  # an empty hub cache
    a = textured(32, 32)
    assert metrics.lpips(a, a) is None
    assert "unavailable offline" in metrics.unavailable("lpips")
    with pytest.raises(ValueError, match="unknown metric"):
        metrics.unavailable("fid")
