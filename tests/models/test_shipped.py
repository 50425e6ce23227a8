"""The checkpoints shipped in checkpoints/ load and render on a fresh clone, and carry a model card."""

import json

import pytest
import torch
from conftest import ROOT

from omnirecon.engine.checkpoint import load_checkpoint
from omnirecon.rays import Sources
from tests.models.test_gpnr import rig

SHIPPED = sorted(p.name for p in (ROOT / "checkpoints").iterdir() if (p / "meta.json").is_file()) \
    if (ROOT / "checkpoints").is_dir() else []


def test_tiny_presets_are_shipped():
    assert {"gpnr-tiny", "ibrnet-tiny", "omnirecon-tiny"} <= set(SHIPPED)


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_checkpoint_renders(name):
    model, meta = load_checkpoint(ROOT / "checkpoints" / name)
    assert meta["preset"] == name
    card = json.loads((ROOT / "checkpoints" / name / "card.json").read_text())
    assert card["steps"] == meta["step"] and card["cpu_seconds"] <= card["cpu_budget_s"] * 1.05
    assert (ROOT / "checkpoints" / name / "MODEL_CARD.md").is_file()
    cams = rig(n=4, w=16, h=16, dtype=torch.float32)
    images = torch.rand(3, 16, 16, 3, generator=torch.Generator().manual_seed(0))
    model.eval()
    features = model.encode(Sources(images, cams[[0, 1, 3]], 2.0, 4.0, "object"))
    out = model.render_view(features, cams[[2]])
    assert out["rgb"].shape == (16, 16, 3) and torch.isfinite(out["rgb"]).all()
    # a float64 target camera (what a Scene holds) is cast to the sources' dtype, same image
    out64 = model.render_view(features, cams[[2]].to(dtype=torch.float64))
    assert out64["rgb"].dtype == torch.float32
    torch.testing.assert_close(out64["rgb"], out["rgb"], atol=1e-5, rtol=0)


SIZED = sorted(str(p.relative_to(ROOT / "checkpoints")) for p in (ROOT / "checkpoints").glob("*/sizes/*")
               if (p / "meta.json").is_file()) if (ROOT / "checkpoints").is_dir() else []


@pytest.mark.parametrize("sized", SIZED)
def test_shipped_weights_at_another_size_are_the_same_model_trained_at_that_size(sized):
    """``checkpoints/<name>/sizes/<px>/``: the same preset and model config as the checkpoint's own weights (the render
    options apart), trained at ``<px>`` px (its meta.json says so) or the own weights unchanged with other render
    options (no tensor stored), recorded on the card, and loaded for a render of that size."""
    from omnirecon.engine.checkpoint import folder_for_size, read_meta, trained_long_side

    name, _, px = sized.split("/")
    own, meta = read_meta(ROOT / "checkpoints" / name), read_meta(ROOT / "checkpoints" / sized)
    from omnirecon.models.registry import RENDER_OPTIONS

    def model(config: dict) -> dict:  # the render options are chosen per weights and size
        return {k: v for k, v in config.items() if k not in RENDER_OPTIONS}

    assert meta["preset"] == own["preset"] and model(meta["model_config"]) == model(own["model_config"])
    card = json.loads((ROOT / "checkpoints" / name / "card.json").read_text())
    if "render" in card["sizes"][px]:  # the own weights with render options chosen at that size: nothing trained
        from omnirecon.engine.checkpoint_check import read_weights

        assert read_weights(ROOT / "checkpoints" / sized / "model.safetensors") == {}
        assert card["sizes"][px]["steps"] == 0 and meta["step"] == own["step"]
        render = {k: v for k, v in meta["model_config"].items() if k in RENDER_OPTIONS}
        assert render == card["sizes"][px]["render"] != {k: v for k, v in own["model_config"].items()
                                                         if k in RENDER_OPTIONS}
    else:
        assert trained_long_side(meta) == int(px) != trained_long_side(own)
        assert card["sizes"][px]["steps"] == meta["step"]
    assert folder_for_size(ROOT / "checkpoints" / name, int(px)) == ROOT / "checkpoints" / sized
    assert folder_for_size(ROOT / "checkpoints" / name, trained_long_side(own)) == ROOT / "checkpoints" / name
    load_checkpoint(ROOT / "checkpoints" / name, long_side=int(px))


def test_omnirecon_tiny_forward_box_on_fern(shared_data):
    """Fern (LLFF: its content box starts ~0.3 in front of the cameras): with the content box alone the shipped
    omnirecon-tiny put an opaque layer near the near plane (target 8 from the ``cpu`` protocol's K = 3 sources:
    21.5 dB, the floor 25.0); the box grown to the cameras gives 25.6 dB."""
    import dataclasses

    from omnirecon.engine.scenes import load_at_resolution
    from omnirecon.metrics import psnr

    scene = load_at_resolution(shared_data("llff/fern"), 64)
    model, _ = load_checkpoint(ROOT / "checkpoints" / "omnirecon-tiny")
    assert model.cfg.forward_box == "cameras"
    sources = Sources.from_scene(scene, [11, 9, 1])
    target, gt = scene.cameras[8].to(dtype=scene.images.dtype), scene.images[8]
    scores = {}
    for box in ("cameras", "content"):
        model.cfg = dataclasses.replace(model.cfg, forward_box=box)
        with torch.no_grad():
            out = model.eval().render_view(model.encode(sources), target)
        scores[box] = psnr(out["rgb"].clamp(0, 1), gt)
        if box == "cameras":
            assert float(out["acc"].mean()) > 0.95  # (content: 0.94, with 22 % of pixels below 0.9)
    assert scores["cameras"] > scores["content"] + 2.0, scores
