"""The mask loss (accumulated opacity against the object mask): exactly zero on a perfect render,
positive and differentiable otherwise, fed from the scenes' masks through the training batch and
switched on by ``omnirecon train --mask-weight``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from omnirecon.cli import main
from omnirecon.data.bank import SceneBank, draw_batch, parse_sources
from omnirecon.data.synth import SynthOptions, generate_scene
from omnirecon.engine.losses import LossModule, mask_loss
from omnirecon.models.registry import build_model
from omnirecon.render.volume import alpha_from_density, weights_from_alpha


def _render(density: torch.Tensor) -> dict[str, torch.Tensor]:
    """Volume-render ``density # [R, S]`` (fine pass) and a blurred copy (coarse pass) as the models do."""
    out = {}
    for key, d in (("", density), ("_coarse", density * 0.5)):
        w, _ = weights_from_alpha(alpha_from_density(d))
        out[f"acc{key}"] = w.sum(-1)
    return out


def test_zero_on_a_perfect_render():
    mask = torch.tensor([1.0, 0.0, 1.0, 0.0])
    # an opaque surface (infinite density at one sample) on the mask, empty space off it, on both passes
    density = torch.zeros(4, 16)
    density[mask > 0, 5] = float("inf")
    out = _render(density)
    assert torch.equal(out["acc"], mask) and torch.equal(out["acc_coarse"], mask)
    assert mask_loss(out, mask, torch.ones(4)).item() == 0.0


def test_positive_and_differentiable_when_wrong():
    mask = torch.tensor([1.0, 0.0, 1.0, 0.0])
    density = torch.full((4, 16), 0.05, requires_grad=True)
    loss = mask_loss(_render(density), mask, torch.ones(4))
    assert loss.item() > 0
    loss.backward()
    g = density.grad.sum(-1)
    assert (g[mask > 0] < 0).all() and (g[mask == 0] > 0).all()  # more density on the object, less off it
    # invalid rays carry no weight
    assert mask_loss(_render(density.detach()), mask, torch.zeros(4)).item() == 0.0


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return generate_scene(tmp_path_factory.mktemp("scenes"), 0, SynthOptions(views=10, resolution=32, max_objects=3,
                                                                             ground=False))


def test_batch_carries_the_mask_and_the_weight_changes_the_loss(scene):
    refs = parse_sources([str(scene)], "train", seed=0, synth_scenes=1, cache=scene.parent, resolution=32,
                         synth_views=10, notes=[])
    bank = SceneBank(refs, None, 32, 1, None)
    ps = bank.get(refs[0][0])
    batch = draw_batch(ps, 3, 6, 64, torch.Generator().manual_seed(0), foreground=0.5)
    assert batch.mask is not None and batch.mask.shape == (64,)
    assert 0 < batch.mask.mean() < 1 and set(batch.mask.unique().tolist()) <= {0.0, 1.0}
    torch.manual_seed(0)
    model = build_model("ibrnet-tiny", {"coarse_samples": 8, "fine_samples": 4})
    args = (batch.sources, batch.rays, batch.rgb, batch.depth)
    torch.manual_seed(1)
    base, _, _ = LossModule(model, 1.0)(*args, batch.mask)
    torch.manual_seed(1)
    with_mask, _, _ = LossModule(model, 1.0, mask_weight=1.0)(*args, batch.mask)
    torch.manual_seed(1)
    out = model.render_rays(model.encode(batch.sources), batch.rays, jitter=True)
    expected = mask_loss(out, batch.mask, out["valid"].float())
    assert with_mask.item() == pytest.approx(base.item() + expected.item(), rel=1e-5) and expected.item() > 0


def test_train_flag(tmp_path, scene, capsys):
    out = tmp_path / "run"
    main(["train", "--model", "ibrnet-tiny", "--model-overrides", "coarse_samples=8", "fine_samples=4",
          "channels=[8,8,16]", "feature_dim=8", "--data", str(scene), "--resolution", "32", "--steps", "3",
          "--rays", "32", "--mask-weight", "0.5", "--val-every", "0", "--ckpt-every", "0", "--out", str(out),
          "--cache", str(tmp_path / "cache"), "--threads", "1", "--no-progress"])
    assert json.loads((out / "config.json").read_text())["train"]["mask_weight"] == 0.5
    capsys.readouterr()
    assert main(["train", "--model", "ibrnet-tiny", "--data", str(scene), "--mask-weight", "-1", "--out",
                 str(tmp_path / "bad"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "--mask-weight must be >= 0" in err and len(err.strip().splitlines()) == 1
