"""``omnirecon train --real-background``: the objects of scenes read from RGBA images on white (as read, the
batches of before), black or a random flat colour per step, the same for the target and its sources.

The scene is a hand-written Blender folder of 8 RGBA views of 16x16 whose alpha holds 0, 1 and fractions."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from omnirecon.data import ReadOptions, load_scene
from omnirecon.data.bank import SceneBank, SceneRef, draw_batch, prepare
from omnirecon.data.io import write_image, write_json
from omnirecon.errors import InputError

SIZE, VIEWS = 16, 8


@pytest.fixture(scope="module")
def rgba(tmp_path_factory) -> tuple[Path, np.ndarray]:
    """A Blender scene (cameras on a circle around the origin) and the alpha of its views ``# [V, H, W]``."""
    root = tmp_path_factory.mktemp("rgba")
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:SIZE, :SIZE] + 0.5
    frames, alphas = [], []
    for i in range(VIEWS):
        r = np.hypot(xx - SIZE / 2 - 0.5 * math.cos(i), yy - SIZE / 2)
        alpha = (np.clip(5.0 - r, 0, 1) * 255).round().astype(np.uint8)  # 1 inside, 0 outside, fractions between
        rgb = rng.integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8)
        write_image(root / "train" / f"r_{i}.png", np.dstack([rgb, alpha]))
        alphas.append(alpha)
        a = 2 * math.pi * i / VIEWS
        eye = np.array([4 * math.cos(a), 4 * math.sin(a), 1.0])
        z = eye / np.linalg.norm(eye)  # OpenGL: the camera looks along -z
        x = np.cross([0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
        c2w[:3, 3] = eye
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": c2w.tolist()})
    write_json(root / "transforms_train.json", {"camera_angle_x": 0.7, "frames": frames})
    return root, np.stack(alphas)


def batches(path: Path, background: str, steps: int = 4):
    """The bank's prepared scene and the batches of generator seeds 0 .. steps - 1."""
    bank = SceneBank([[SceneRef(path)]], None, SIZE, background=background)
    ps = bank.get(SceneRef(path))
    return ps, [draw_batch(ps, 3, 6, 64, torch.Generator().manual_seed(s), 0.5) for s in range(steps)]


def test_white_is_the_batch_of_before(rgba):
    """The default and ``white`` give the batches of a scene read as before (composited on white by the reader)."""
    path, _ = rgba
    ps, got = batches(path, "white")
    assert ps.clear is None
    before = prepare(load_scene(path, options=ReadOptions()), path.name)
    for s, b in enumerate(got):
        ref = draw_batch(before, 3, 6, 64, torch.Generator().manual_seed(s), 0.5)
        assert torch.equal(b.rgb, ref.rgb) and torch.equal(b.sources.images, ref.sources.images)
        assert b.target == ref.target and b.source_ids == ref.source_ids and torch.equal(b.mask, ref.mask)
        assert torch.equal(b.rays.directions, ref.rays.directions)


def test_black_clears_the_background_of_target_and_sources_alike(rgba):
    path, alpha = rgba
    ps, black = batches(path, "black")
    _, white = batches(path, "white")
    alpha = torch.from_numpy(alpha).float() / 255  # [V, H, W]
    assert ps.clear is not None and torch.allclose(ps.clear[..., 0], 1 - alpha, atol=1e-6)
    for b, w in zip(black, white):
        assert (b.target, b.source_ids) == (w.target, w.source_ids)  # the same draws as a white batch
        assert torch.equal(b.rays.directions, w.rays.directions)
        src_a = alpha[b.source_ids]  # [K, H, W]
        assert (b.sources.images[src_a == 0] == 0).all()  # masked-out source pixels are black
        assert torch.equal(b.sources.images[src_a == 1], w.sources.images[src_a == 1])  # the object is unchanged
        clear = (w.rgb - b.rgb).mean(-1)  # [R] the rays' 1 - alpha (on white minus on black)
        out, on = clear > 1 - 1e-6, clear < 1e-6
        assert out.any() and on.any()
        assert (b.rgb[out] == 0).all() and torch.equal(b.rgb[on], w.rgb[on])  # masked-out target rays are black


def test_random_is_seeded_and_shared_by_target_and_sources(rgba):
    path, alpha = rgba
    alpha = torch.from_numpy(alpha).float() / 255
    _, white = batches(path, "white", steps=12)
    _, black = batches(path, "black", steps=12)
    _, one = batches(path, "random", steps=12)
    _, two = batches(path, "random", steps=12)
    colours = []
    for a, b, w, k in zip(one, two, white, black):
        assert torch.equal(a.rgb, b.rgb) and torch.equal(a.sources.images, b.sources.images)  # the same seed
        assert (a.target, a.source_ids) == (w.target, w.source_ids)
        out = alpha[a.source_ids] == 0  # [K, H, W]
        colour = a.sources.images[out][0]  # [3]
        assert torch.equal(a.sources.images[out], colour.expand(int(out.sum()), 3))  # one flat colour per step
        clear = (w.rgb - k.rgb).mean(-1)  # [R]
        assert (clear > 1 - 1e-6).any()
        assert torch.allclose(a.rgb[clear > 1 - 1e-6], colour.expand(int((clear > 1 - 1e-6).sum()), 3))  # the target's
        colours.append(colour)
    kinds = {"white" if (c == 1).all() else "black" if (c == 0).all() else "colour" for c in colours}
    assert kinds == {"white", "black", "colour"}  # 12 steps: each kind at least once


def test_unknown_background_is_refused(rgba):
    path, _ = rgba
    with pytest.raises(InputError, match="unknown training background"):
        SceneBank([[SceneRef(path)]], None, SIZE, background="grey")
    with pytest.raises(InputError, match="unknown training background"):
        prepare(load_scene(path), path.name, background="grey")
