"""Image quality metrics for evaluation: PSNR, SSIM, ST-LPIPS and (when possible offline) LPIPS.

Every function takes a prediction and a ground truth of shape ``[H, W, 3]`` with values in
``[0, 1]`` (torch tensors or NumPy arrays; they are compared in float64 for PSNR and float32 for
the networks) and returns a Python float.

* :func:`psnr` is ``-10 log10(MSE)`` over the ``[0, 1]`` image, optionally only over the pixels of
  a mask. Identical images give ``inf`` (no cap).
* :func:`ssim` is Wang et al. 2004 SSIM as every NeRF paper's skimage/TF code computes it: an
  11 x 11 Gaussian window with sigma 1.5, ``K = (0.01, 0.03)``, data range 1, evaluated where the
  window fits inside the image ("valid"), averaged over pixels and channels. It equals
  ``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=1, channel_axis=-1)`` (within 1e-5 in our tests), not
  skimage's default (uniform 7 x 7 window).
* :func:`st_lpips` is the *shift-tolerant* LPIPS of Ghildyal & Liu (ECCV 2022) with the AlexNet
  trunk from ``stlpips-pytorch``, whose wheel ships every weight it needs, so it always works
  offline. Its values are **not** comparable with the LPIPS numbers papers report; results name it
  ``st_lpips_alex``.
* :func:`lpips` is standard LPIPS v0.1 (AlexNet) from the ``lpips`` package, computed only when
  the package *and* its torchvision backbone weights are already on the machine; it never
  downloads. Otherwise it returns ``None`` and :func:`unavailable` says why.

The networks are loaded once on first use and cached per device.
"""

from __future__ import annotations

import importlib.util
import math
import sys
import types
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

SSIM_WINDOW = 11
"""Side of the Gaussian SSIM window in pixels."""
SSIM_SIGMA = 1.5
"""Standard deviation of the SSIM window in pixels."""
LPIPS_BACKBONE = "alexnet-owt-7be5be79.pth"
"""torchvision's AlexNet weights file that standard LPIPS needs in the torch hub cache."""

_NETS: dict[tuple[str, str], torch.nn.Module] = {}
_REASONS: dict[str, str] = {}


def _image(x, name: str) -> Tensor:
    """``x`` as a float tensor ``# [H, W, 3]``; ValueError for any other shape."""
    t = torch.as_tensor(np.asarray(x) if not torch.is_tensor(x) else x)
    if t.dim() != 3 or t.shape[-1] != 3:
        raise ValueError(f"{name} must be an [H, W, 3] image, got shape {tuple(t.shape)}")
    return t.detach().cpu()


def _pair(pred, gt) -> tuple[Tensor, Tensor]:
    p, g = _image(pred, "pred"), _image(gt, "gt")
    if p.shape != g.shape:
        raise ValueError(f"pred and gt differ in shape: {tuple(p.shape)} vs {tuple(g.shape)}")
    return p, g


# ---------------------------------------------------------------------- PSNR / SSIM
def psnr(pred, gt, mask=None) -> float:
    """Peak signal-to-noise ratio in dB of ``pred`` against ``gt`` (peak 1).

    Args:
        pred: Rendered image in [0, 1]. ``# [H, W, 3]``
        gt: Ground truth in [0, 1]. ``# [H, W, 3]``
        mask: Optional pixels to score (bool or 0/1). ``# [H, W]``; the MSE is averaged over
            those pixels and the three channels.

    Returns:
        ``-10 log10(MSE)``; ``inf`` for identical images, ``nan`` for an empty mask.
    """
    p, g = _pair(pred, gt)
    err = (p.double() - g.double()) ** 2  # [H, W, 3]
    if mask is not None:
        m = torch.as_tensor(np.asarray(mask) if not torch.is_tensor(mask) else mask).cpu().bool()
        if m.shape != p.shape[:2]:
            raise ValueError(f"mask must be [H, W] = {list(p.shape[:2])}, got {list(m.shape)}")
        if not m.any():
            return math.nan
        err = err[m]  # [M, 3]
    mse = float(err.mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def ssim(pred, gt) -> float:
    """Structural similarity (Wang et al. 2004; 11 x 11 Gaussian window, sigma 1.5, data range 1).

    Computed with ``pytorch_msssim.ssim`` (valid-window convolution, mean over pixels and channels).
    Both image sides must be at least 11 pixels.
    """
    from pytorch_msssim import ssim as _ssim

    p, g = _pair(pred, gt)
    if min(p.shape[:2]) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW} px per side, got {tuple(p.shape[:2])}")
    x = p.float().permute(2, 0, 1)[None]  # [1, 3, H, W]
    y = g.float().permute(2, 0, 1)[None]
    with torch.no_grad():
        return float(_ssim(x, y, data_range=1.0, size_average=True, win_size=SSIM_WINDOW, win_sigma=SSIM_SIGMA,
                           K=(0.01, 0.03)))


# ---------------------------------------------------------------------- perceptual metrics
def st_lpips(pred, gt, device: str | torch.device = "cpu") -> float | None:
    """Shift-tolerant LPIPS (AlexNet trunk) from ``stlpips-pytorch``; lower is better.

    Returns ``None`` when the package is not installed (see :func:`unavailable`). Inputs are
    mapped from [0, 1] to [-1, 1] as the package expects.
    """
    net = _st_lpips_net(device)
    return None if net is None else _perceptual(net, pred, gt, device)


def lpips(pred, gt, device: str | torch.device = "cpu") -> float | None:
    """Standard LPIPS v0.1 (AlexNet) from the ``lpips`` package; lower is better.

    Runs only when ``lpips`` is importable and torchvision's ``alexnet-owt-7be5be79.pth`` is already
    in the torch hub cache (``$TORCH_HOME/hub/checkpoints``); nothing is ever downloaded. Returns
    ``None`` otherwise (see :func:`unavailable`).
    """
    net = _lpips_net(device)
    return None if net is None else _perceptual(net, pred, gt, device)


def unavailable(name: str) -> str | None:
    """Why metric ``name`` (``"st_lpips"`` or ``"lpips"``) returns ``None``; ``None`` if it works."""
    loaders = {"st_lpips": _st_lpips_net, "lpips": _lpips_net}
    if name not in loaders:
        raise ValueError(f"unknown metric {name!r}; use one of {sorted(loaders)}")
    loaders[name]("cpu")
    return _REASONS.get(name)


def _perceptual(net: torch.nn.Module, pred, gt, device) -> float:
    p, g = _pair(pred, gt)
    x = p.float().permute(2, 0, 1)[None].to(device) * 2 - 1  # [1, 3, H, W] in [-1, 1]
    y = g.float().permute(2, 0, 1)[None].to(device) * 2 - 1
    with torch.no_grad():
        return float(net(x, y).reshape(()))


@contextmanager
def _stub_modules(names: tuple[str, ...]):
    """Temporarily register empty stand-ins for ``names`` that are not installed.

    ``stlpips-pytorch`` imports ``IPython.embed``, ``torchsummary.summary`` and ``torchvision.models``
    at module level but uses none of them for the AlexNet shift-tolerant trunk. The stand-ins are
    removed again afterwards, so no other library ever sees them; calling anything on them raises.
    """

    def missing(*_args, **_kwargs):
        raise RuntimeError("this part of stlpips-pytorch needs IPython/torchsummary/torchvision, which are "
                           "not installed; only the AlexNet shift-tolerant metric is supported")

    added = []
    for name in names:
        if name in sys.modules or importlib.util.find_spec(name) is not None:
            continue
        mod = types.ModuleType(name)
        mod.__getattr__ = lambda attr, _m=missing: _m  # type: ignore[method-assign]
        sys.modules[name] = mod
        added.append(name)
    try:
        yield
    finally:
        for name in added:
            sys.modules.pop(name, None)


def _cached_net(name: str):
    """Decorate a loader that returns a network or, when it cannot, the reason (a string): the result is a
    ``get(device)`` that loads once per device, keeps the network frozen in eval mode, and after a failure
    returns None at once (the reason stays in ``_REASONS[name]``)."""

    def wrap(load):
        def get(device) -> torch.nn.Module | None:
            key = (name, str(device))
            if key not in _NETS and name not in _REASONS:
                net = load()
                if isinstance(net, str):
                    _REASONS[name] = net
                else:
                    _NETS[key] = net.eval().requires_grad_(False).to(device)
            return _NETS.get(key)

        return get

    return wrap


@_cached_net("st_lpips")
def _st_lpips_net():
    if importlib.util.find_spec("stlpips_pytorch") is None:
        return "stlpips-pytorch is not installed (pip install stlpips-pytorch)"
    with _stub_modules(("IPython", "torchsummary", "torchvision")):
        from stlpips_pytorch import stlpips as _st
    weights = Path(_st.__file__).parent / "weights" / "vST0.0" / "alex_shift_tolerant.pth"
    if not weights.is_file():
        return f"stlpips-pytorch has no {weights.name} (reinstall the package)"
    net = _st.LPIPS(net="alex", variant="shift_tolerant", pretrained=False, verbose=False)
    # The package loads with strict=False; load strictly here (only the ``lins`` alias of lin0..4 may be
    # absent) so that a renamed layer cannot silently leave a random trunk.
    missing, unexpected = net.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True),
                                              strict=False)
    if unexpected or any(not k.startswith("lins.") for k in missing):
        return f"{weights.name} does not match the network (missing {missing[:3]})"
    return net


@_cached_net("lpips")
def _lpips_net():
    if importlib.util.find_spec("lpips") is None or importlib.util.find_spec("torchvision") is None:
        return "unavailable offline: the lpips package (with torchvision) is not installed"
    backbone = Path(torch.hub.get_dir()) / "checkpoints" / LPIPS_BACKBONE
    if not backbone.is_file():
        return f"unavailable offline: torchvision backbone {backbone} is not cached"
    import lpips as _lp

    return _lp.LPIPS(net="alex", verbose=False)
