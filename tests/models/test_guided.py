"""Surface-guided rendering (omnirecon.models.guided) against its reference twin, the full path: off it is
``render_view``; rays without a prior are the full path's bit for bit; on a small procedural scene the guided
render of each shipped checkpoint stays within a stated PSNR of the full render. Upsampled guided rendering: each
model's ``colour_weights`` reproduce its ``rgb``, and the blend at full size stays closer to the full render than
the small render upsampled."""

import dataclasses

import pytest
import torch
from conftest import ROOT

from omnirecon.data import load_scene
from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.engine.checkpoint import load_checkpoint
from omnirecon.errors import InputError
from omnirecon.metrics import psnr
from omnirecon.models.guided import (
    GuidedOptions,
    band_depths,
    bilinear_cells,
    blend_sources,
    from_unit,
    grid_units,
    pixel_bands,
    render_guided,
    strongest_samples,
    to_unit,
)
from omnirecon.rays import Rays, Sources
from omnirecon.render.volume import sample_along_rays

MODELS = ("gpnr-tiny", "ibrnet-tiny", "omnirecon-tiny")


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    return generate_scene(tmp_path_factory.mktemp("guided"), 900_321, SynthOptions(rig="forward", resolution=48,
                                                                                 views=12))


@pytest.fixture(scope="module")
def scene(scene_path):
    return load_scene(scene_path).normalized()


def _setup(name, scene):
    model, _ = load_checkpoint(ROOT / "checkpoints" / name)
    model.eval()
    with torch.no_grad():
        features = model.encode(Sources.from_scene(scene, [1, 3, 5]))
    return model, features, scene.cameras[[4]].to(dtype=scene.images.dtype)


def test_units_round_trip_and_bands():
    """The sampling parameter is inverse depth on forward rigs (0 at near, 1 at far); a pixel's band holds the
    prior depths of its 2x2 cells plus ``band``; untrusted cells and wide spreads leave no prior."""
    z = torch.tensor([1.0, 2.0, 4.0])
    u = to_unit(z, 1.0, 4.0, True)
    torch.testing.assert_close(u, torch.tensor([0.0, 2 / 3, 1.0]))
    torch.testing.assert_close(from_unit(u, 1.0, 4.0, True), z)
    torch.testing.assert_close(to_unit(z, 1.0, 4.0, False), torch.tensor([0.0, 1 / 3, 1.0]))
    prior = torch.full((4, 4), 2.0)
    prior[:, 2:] = 2.2  # a small step between columns 1 and 2
    prior[0, 0] = float("nan")  # an untrusted cell
    opts = GuidedOptions(band=0.05, max_spread=0.25)
    lo, hi = pixel_bands(prior, 8, 8, 1.0, 4.0, False, opts)  # 2x upsampled
    assert torch.isnan(lo[0, 0]) and torch.isnan(lo[1, 1])  # cells touching the NaN one
    u2, u22 = float(to_unit(torch.tensor(2.0), 1.0, 4.0, False)), float(to_unit(torch.tensor(2.2), 1.0, 4.0, False))
    assert lo[6, 0] == pytest.approx(u2 - 0.05) and hi[6, 0] == pytest.approx(u2 + 0.05)
    assert lo[6, 4] == pytest.approx(u2 - 0.05) and hi[6, 4] == pytest.approx(u22 + 0.05)  # the step: both sides
    lo, _ = pixel_bands(prior, 8, 8, 1.0, 4.0, False, GuidedOptions(band=0.05, max_spread=0.05))
    assert torch.isnan(lo[6, 4]) and not torch.isnan(lo[6, 0])  # wider than max_spread: full sampling
    z = band_depths(torch.tensor([0.4]), torch.tensor([0.5]), 1.0, 4.0, False, GuidedOptions(band_samples=3,
                                                                                          guard_samples=2))
    torch.testing.assert_close(to_unit(z, 1.0, 4.0, False), torch.tensor([[0.25, 0.4, 0.45, 0.5, 0.75]]))


def test_grid_layout_is_the_full_paths_own_samples():
    """The grid layout: every sample is one of the full path's (``sample_along_rays`` with ``grid_samples``), none
    twice; the guards span the ray (both ends) and the band's samples are the other grid points nearest the centre;
    more samples than the grid holds is an input error naming the options."""
    assert torch.equal(grid_units(torch.tensor([0.3]), 32, 3, 5) * 31,
                       torch.tensor([[0.0, 8.0, 9.0, 10.0, 11.0, 16.0, 23.0, 31.0]]))  # guards 0 8 16 23 31; 9-11
    opts = GuidedOptions(layout="grid", band_samples=4, guard_samples=6, grid_samples=32)
    lo, hi = torch.tensor([0.0, 0.41, 0.9]), torch.tensor([0.05, 0.47, 1.0])
    for inverse in (False, True):
        z = band_depths(lo, hi, 1.0, 4.0, inverse, opts)  # [3, 10]
        full = sample_along_rays(torch.ones(1), torch.full((1,), 4.0), 32, inverse_depth=inverse)[0]  # [32]
        at = (z[..., None] - full).abs().argmin(-1)  # [3, 10] grid index of each sample
        torch.testing.assert_close(z, full[at])
        assert all(len(set(r.tolist())) == 10 for r in at) and (at[:, 0] == 0).all() and (at[:, -1] == 31).all()
        centre = (lo + hi) / 2 * 31
        guards = {0, 6, 12, 19, 25, 31}  # round(linspace(0, 31, 6))
        for r, c in zip(at, centre.tolist()):
            nearest = sorted(set(range(32)) - guards, key=lambda i, c=c: abs(i - c))[:4]
            assert set(r.tolist()) == guards | set(nearest)

    class Tiny:  # a model class without family values: the "other" row, on its own 8-sample grid
        cfg = type("Cfg", (), {"coarse_samples": 8})()

    assert opts.resolved(Tiny()).grid_samples == 32  # given: kept
    with pytest.raises(InputError, match="exceed --guided.grid_samples"):
        dataclasses.replace(opts, grid_samples=None).resolved(Tiny())


@pytest.mark.parametrize("name", MODELS)
def test_off_and_rays_without_prior_are_the_full_path(name, scene):
    """Off: ``render_view`` itself. On, with a prior on the left half only: the right half's pixels are the full
    render's bit for bit, the left half's were guided."""
    model, features, cam = _setup(name, scene)
    with torch.no_grad():
        full = model.render_view(features, cam)
        off = render_guided(model, features, cam, GuidedOptions())
        assert torch.equal(off["rgb"], full["rgb"]) and not off["guided"].any()
        prior = full["depth"].float() / (full["acc"].float().clamp_min(1e-6) if "acc" in full else 1.0)
        prior[:, cam.width // 2:] = float("nan")
        out = render_guided(model, features, cam, GuidedOptions(on=True, max_spread=1.0, min_opacity=0.0, upsample=1),
                            prior=prior)
    right = slice(cam.width // 2 + 1, None)  # (the column beside the NaN half reads it as a 2x2 neighbour)
    assert not out["guided"][:, right].any() and out["guided"][:, : cam.width // 2 - 1].all()
    assert torch.equal(out["rgb"][:, right], full["rgb"][:, right])
    assert not torch.equal(out["rgb"], full["rgb"])  # the guided half was rendered differently


@pytest.mark.parametrize("name,floor", [("gpnr-tiny", 30.0), ("ibrnet-tiny", 20.0), ("omnirecon-tiny", 33.0)])
def test_guided_close_to_full(name, floor, scene):
    """The defaults at full size (prior: the model's own render at 1/4 size) on a held-out procedural forward scene
    at 48 px: the guided render is within ``floor`` dB PSNR of the full render (measured at the time of writing: see
    the assertion message), and most pixels were guided."""
    model, features, cam = _setup(name, scene)
    with torch.no_grad():
        full = model.render_view(features, cam)["rgb"]
        out = render_guided(model, features, cam, GuidedOptions(on=True, upsample=1))
    score = psnr(out["rgb"].clamp(0, 1), full.clamp(0, 1))
    frac = float(out["guided"].float().mean())
    assert score >= floor and frac > 0.5, f"{name}: {score:.2f} dB to the full render, {frac:.0%} guided"


def test_eval_guided_option_records_its_settings(run_cli, scene_path, tmp_path):
    """``eval --guided.on`` renders guided and records the resolved options; a bad value is one line, exit 2."""
    import json

    args = ["eval", "--ckpt", ROOT / "checkpoints" / "omnirecon-tiny", "--scenes", scene_path, "--num-views", 3,
            "--max-targets", 1, "--protocol-set", "cpu", "--no-save-images", "--threads", 1]
    rc, _, err = run_cli([*args, "--guided.on", "--out", tmp_path / "on"])
    assert rc == 0, err
    guided = json.loads((tmp_path / "on" / "results.json").read_text())["guided"]
    assert guided["on"] and guided["layout"] == "grid" and guided["band_samples"] == 3 \
        and guided["grid_samples"] == 32  # Omni-Recon's family values, its own full-path samples
    rc, _, err = run_cli([*args, "--guided.band", "2", "--out", tmp_path / "bad"])
    assert rc == 2 and "--guided.band must be in [0, 1]" in err and "Traceback" not in err
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize("name", MODELS)
def test_colour_weights_reproduce_rgb(name, scene):
    """``colour_weights`` blended over the source colours at ``colour_depths`` (:func:`blend_sources`) is the
    model's ``rgb``, on its full path and on a guided pass; asking for them leaves every other output unchanged."""
    model, features, cam = _setup(name, scene)
    cam = cam.rescaled(0.5).to(dtype=features.sources.images.dtype)  # 24 px: the identity holds per ray
    rays = Rays.from_image(cam)
    with torch.no_grad():
        plain = model.render_view(features, cam)
        out = model.render_view(features, cam, colour_weights=True)
        z = out["colour_depths"].reshape(len(rays), -1)[:, :6]
        guided = model.render_view(features, cam, pixels=torch.arange(len(rays)), depths=z, colour_weights=True)
    assert all(torch.equal(plain[k], out[k]) for k in plain)
    for o in (out, guided):
        w = o["colour_weights"].reshape(len(rays), *o["colour_weights"].shape[-2:])
        blend = blend_sources(features.sources, rays, o["colour_depths"].reshape(len(rays), -1), w)
        torch.testing.assert_close(blend, o["rgb"].reshape(-1, 3), atol=1e-4, rtol=0)


@pytest.mark.parametrize("name,floor", [("gpnr-tiny", 42.0), ("ibrnet-tiny", 40.0), ("omnirecon-tiny", 36.0)])
def test_upsampled_close_to_full_and_sharper_than_the_small_render(name, floor, scene):
    """``upsample=2`` on the 48-px procedural view: within ``floor`` dB of the full render (measured at the time of
    writing: see the message), closer to it than the 24-px render upsampled bilinearly, and pixels on depth edges
    rendered at full size; the family defaults upsample too, and ``upsample=1`` renders at full size."""
    import torch.nn.functional as F

    model, features, cam = _setup(name, scene)
    opts = GuidedOptions(on=True, upsample=2, small_path="guided")
    with torch.no_grad():
        full = model.render_view(features, cam)["rgb"].clamp(0, 1)
        up = render_guided(model, features, cam, opts)
        small = render_guided(model, features, cam.rescaled(0.5), dataclasses.replace(opts, upsample=1))["rgb"]
        one = render_guided(model, features, cam, dataclasses.replace(opts, upsample=1))
        default = render_guided(model, features, cam, GuidedOptions(on=True))
    naive = F.interpolate(small.permute(2, 0, 1)[None].float(), size=full.shape[:2], mode="bilinear",
                          align_corners=False)[0].permute(1, 2, 0)
    score, base = psnr(up["rgb"].clamp(0, 1), full), psnr(naive.clamp(0, 1), full)
    edges = float((~up["upsampled"]).float().mean())
    assert score >= floor and score > base + 1.0 and 0.0 < edges < 0.5, \
        f"{name}: {score:.2f} dB to the full render, small render upsampled {base:.2f}, {edges:.0%} at full size"
    assert "upsampled" not in one and "upsampled" in default


def test_upsampled_falls_back_where_rgb_is_not_a_blend(scene):
    """GPNR with its feature head as ``rgb`` returns no colour weights: ``upsample`` renders guided at full size."""
    model, features, cam = _setup("gpnr-tiny", scene)
    model.cfg = dataclasses.replace(model.cfg, output="features")
    with torch.no_grad():
        up = render_guided(model, features, cam, GuidedOptions(on=True, upsample=2))
        flat = render_guided(model, features, cam, GuidedOptions(on=True, upsample=1))
    assert "upsampled" not in up and torch.equal(up["rgb"], flat["rgb"])


def test_upsampled_from_the_full_path(scene):
    """``small_path="full"`` (IBRNet's family default): the small view on the full path, none of its pixels guided,
    blended at full size within a stated PSNR of the full render (measured at the time of writing: see the message)."""
    model, features, cam = _setup("ibrnet-tiny", scene)
    with torch.no_grad():
        full = model.render_view(features, cam)["rgb"].clamp(0, 1)
        up = render_guided(model, features, cam, GuidedOptions(on=True, upsample=3, small_path="full"))
    score = psnr(up["rgb"].clamp(0, 1), full)
    assert score >= 44.0 and not up["guided"][up["upsampled"]].any(), f"{score:.2f} dB to the full render"


def test_bilinear_cells_and_strongest_samples():
    """A 4-px row over a 2-cell one: the outer pixels take their own cell, the inner ones 3/4 of theirs and 1/4 of
    the other; shares sum to 1. The strongest samples keep a row's total weight, in depth order."""
    cells, share = bilinear_cells(1, 4, 1, 2)
    mix = torch.zeros(4, 2).index_put_((torch.arange(4).repeat(4), cells.flatten()), share.flatten(), accumulate=True)
    torch.testing.assert_close(mix, torch.tensor([[1.0, 0.0], [0.75, 0.25], [0.25, 0.75], [0.0, 1.0]]))
    depths = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    weights = torch.tensor([[[0.1, 0.0], [0.0, 0.4], [0.3, 0.1], [0.1, 0.0]]])  # [1, 4, 2]: masses .1 .4 .4 .1
    z, w = strongest_samples(depths, weights, 2)
    assert torch.equal(z, torch.tensor([[2.0, 3.0]]))
    torch.testing.assert_close(w.sum(), weights.sum())
    torch.testing.assert_close(w[0, :, 1], torch.tensor([0.4, 0.1]) * 1.0 / 0.8)
    assert strongest_samples(depths, weights, 8)[0] is depths
