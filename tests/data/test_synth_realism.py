"""Realism options of ``omnirecon synth``: off by default (nothing recorded, nothing changed), each one
deterministic by seed, changing the colour images only (ground truth untouched), and drawing different
random effects for different seeds where it is random."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from omnirecon.data.synth import SynthOptions, generate_scene
from omnirecon.data.synth.layout import make_layout
from omnirecon.data.synth.photo import REALISM, camera_effects, scene_light
from omnirecon.errors import InputError

BASE = SynthOptions(rig="object", views=3, resolution=32)
OPTIONS = {"specular": 0.5, "light_variation": 1.0, "noise": 0.03, "exposure": 0.4, "white_balance": 0.08,
           "vignetting": 0.4, "blur": 0.8}
RANDOM = {"light_variation", "noise", "exposure", "white_balance"}
"""Options whose effect is a random draw (the others are fixed functions of the options)."""


def _files(folder: Path, pattern: str) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.glob(pattern))}


def _rgb(folder: Path) -> dict[str, np.ndarray]:
    return {p.name: np.asarray(Image.open(p), dtype=np.float64) for p in sorted(folder.glob("*/r_[0-9].png"))}


def _gt(folder: Path) -> dict[str, str]:
    return {k: hashlib.sha256(v).hexdigest() for k, v in _files(folder, "*/r_*_*.png").items()}


@pytest.fixture(scope="module")
def plain(tmp_path_factory) -> Path:
    return generate_scene(tmp_path_factory.mktemp("plain"), 5, BASE)


def test_defaults_are_off_and_leave_no_trace(plain):
    assert set(REALISM) <= {f for f in SynthOptions.__dataclass_fields__}
    assert all(getattr(BASE, k) == v for k, v in REALISM.items())
    record = json.loads((plain / "scene.json").read_text())
    assert not set(REALISM) & set(record["options"])  # scene.json as written before the options existed
    assert set(record["light"]) == {"direction", "ambient", "intensity"}
    rgb = np.random.default_rng(0).random((8, 8, 3)).astype(np.float32)
    assert camera_effects(rgb, BASE, 5, 0) is rgb
    light = make_layout(np.random.default_rng(5), "object", 3, True, (2, 6), 1).light
    assert scene_light(light, BASE, 5) is light


@pytest.mark.parametrize("name", sorted(OPTIONS))
def test_each_option_is_deterministic_by_seed(tmp_path, plain, name):
    options = replace(BASE, **{name: OPTIONS[name]})
    a = generate_scene(tmp_path / "a", 5, options)
    b = generate_scene(tmp_path / "b", 5, options)
    assert _files(a, "**/*.png") == _files(b, "**/*.png")
    assert (a / "scene.json").read_text() == (b / "scene.json").read_text()
    assert json.loads((a / "scene.json").read_text())["options"][name] == OPTIONS[name]
    assert _gt(a) == _gt(plain)  # depth, normals, labels, masks: exact whatever the photometry
    ra, rp = _rgb(a), _rgb(plain)
    assert any(np.abs(ra[k] - rp[k]).max() > 2 for k in rp)  # the images did change
    if name in RANDOM:  # another seed draws other effects: compare the effect, not the scene
        other = replace(BASE, **{name: OPTIONS[name]})
        rgb = np.full((16, 16, 3), 0.5, dtype=np.float32)
        if name == "light_variation":
            light = make_layout(np.random.default_rng(5), "object", 3, True, (2, 6), 1).light
            assert scene_light(light, other, 5) != scene_light(light, other, 6)
        else:
            assert not np.array_equal(camera_effects(rgb, other, 5, 0), camera_effects(rgb, other, 6, 0))
            assert not np.array_equal(camera_effects(rgb, other, 5, 0), camera_effects(rgb, other, 5, 1))


def test_specular_only_adds_light_and_depends_on_the_view(plain, tmp_path):
    shiny = generate_scene(tmp_path, 5, replace(BASE, specular=0.5))
    rs, rp = _rgb(shiny), _rgb(plain)
    assert all((rs[k] >= rp[k] - 1).all() for k in rp)  # a highlight never darkens (up to 8-bit rounding)
    gain = [float((rs[k] - rp[k]).sum()) for k in sorted(rp)]
    assert len(set(np.round(gain, 3))) > 1  # the highlight differs between views


def test_effects_on_a_flat_image():
    rgb = np.full((32, 32, 3), 0.5, dtype=np.float32)
    vig = camera_effects(rgb, replace(BASE, vignetting=0.4), 0, 0)
    assert vig[16, 16, 0] > vig[0, 0, 0] and abs(vig[0, 0, 0] - 0.5 * (1 - 0.4 * (31.5 / 32 - 0.5) ** 2 / 0.25)) < 1e-3
    assert np.allclose(camera_effects(rgb, replace(BASE, blur=1.0), 0, 0), 0.5)  # blur keeps a flat image
    noisy = camera_effects(rgb, replace(BASE, noise=0.04), 0, 0)
    assert 0.02 < noisy.std() < 0.04  # sqrt(0.04^2 * 0.5 + 0.01^2) = 0.030


def test_bad_values_are_one_line_errors():
    with pytest.raises(InputError, match="--noise must be"):
        replace(BASE, noise=-0.1).check()
    with pytest.raises(InputError, match=r"--vignetting must be in \[0, 1\]"):
        replace(BASE, vignetting=1.5).check()
    with pytest.raises(InputError, match="--aspect must be"):
        replace(BASE, aspect=0.0).check()


def test_aspect_crops_the_square_scene_and_reads_at_its_size(tmp_path, plain):
    """A 4:3 scene (``aspect`` 0.75, DTU's) is the square one's middle rows: the same layout, horizontal field of
    view and pixel centres, so every image equals the square image's crop; the reader sees its size; the square
    scene's scene.json records no aspect."""
    from omnirecon.data import load_scene

    wide = generate_scene(tmp_path / "wide", 5, replace(BASE, aspect=0.75))  # 32 x 24
    square, cropped = load_scene(plain), load_scene(wide)
    assert (cropped.width, cropped.height) == (32, 24)
    assert json.loads((wide / "scene.json").read_text())["options"]["aspect"] == 0.75
    assert "aspect" not in json.loads((plain / "scene.json").read_text())["options"]
    top = (32 - 24) // 2
    assert np.abs(cropped.images.numpy() - square.images[:, top:top + 24].numpy()).max() <= 1 / 255
    assert np.abs(cropped.depths.numpy() - square.depths[:, top:top + 24].numpy()).max() <= 1e-3
    portrait = generate_scene(tmp_path / "tall", 5, replace(BASE, aspect=2.0))
    assert (load_scene(portrait).width, load_scene(portrait).height) == (16, 32)
