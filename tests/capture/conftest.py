"""Fixtures shared by the capture tests."""

import shutil

import numpy as np
import pytest

from omnirecon.data.io import write_image


@pytest.fixture
def views_with_noise(tmp_path):
    """``make(photos, noise)``: a folder of the first 6 views of ``photos`` plus ``noise`` images of
    uniform noise (``noise_<i>.png``, 256x256, seed 0) that no photo matches."""

    def make(photos, noise: int):
        d = tmp_path / "noisy"
        d.mkdir()
        for i in range(6):
            shutil.copyfile(photos / f"r_{i}.png", d / f"r_{i}.png")
        g = np.random.default_rng(0)
        for i in range(noise):
            write_image(d / f"noise_{i}.png", g.uniform(size=(256, 256, 3)).astype(np.float32))
        return d

    return make
