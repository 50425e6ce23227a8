"""Shared fixtures. Real scenes come from ../shared/data (present in CI, absent in a user's clone)."""

import os
from pathlib import Path

# The processes the tests start (python -m bench ..., the CLI, the installed wheel) run one torch thread as the tests do
# (below), and torch.compile compiles in its own process instead of starting a pool of compile workers: the two
# workers of `pytest -n 2` already share the 2 cores.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("TORCHINDUCTOR_COMPILE_THREADS", "1")

import pytest  # noqa: E402
import torch  # noqa: E402

# Tests run small tensors: one thread is as fast, and on a shared 2-core machine two threads ran
# TSDF fusion 25x and the Omni-Recon overfit 17x slower than one.
torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]
"""The repository root (tests mirror the package in subfolders; import ROOT from here)."""
SHARED_DATA = Path(os.environ.get("OMNIRECON_SHARED_DATA", ROOT.parent / "shared" / "data"))


def shared_scene(rel: str) -> Path:
    """Path of a scene under ../shared/data, or skip the test with the reason."""
    path = SHARED_DATA / rel
    if not path.is_dir():
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI must have {path} (the shared scenes sit beside the clone in CI)")
        pytest.skip(f"{path} not found: the real scenes live in ../shared/data beside the clone "
                    "(set OMNIRECON_SHARED_DATA to point elsewhere)")
    return path


@pytest.fixture
def shared_data():
    return shared_scene


def require(available: bool, reason: str) -> None:
    """Skip the calling test when an optional system component is missing, or fail under ``CI=true``
    (CI installs it: `make setup` runs scripts/setup_system.sh)."""
    if available:
        return
    if os.environ.get("CI") == "true":
        pytest.fail(f"CI must have it: {reason}")
    pytest.skip(reason)


@pytest.fixture(scope="session")
def gl():
    """A headless EGL context (moderngl): skip without one, fail under ``CI=true``."""
    from omnirecon.render import raster

    require(raster.gl_available(), f"no headless EGL context: {raster.gl_unavailable_reason()}")


@pytest.fixture
def run_cli(capsys):
    """``omnirecon ARGS`` in-process: returns ``(exit code, stdout, stderr)``. Unexpected exceptions propagate."""
    from omnirecon.cli import main

    def run(args):
        capsys.readouterr()
        code = main([str(a) for a in args])
        cap = capsys.readouterr()
        return code, cap.out, cap.err

    return run


@pytest.fixture
def views_with_noise(tmp_path):
    """``make(photos, noise)``: a folder of the first 6 views of ``photos`` plus ``noise`` images of
    uniform noise (``noise_<i>.png``, 256x256, seed 0) that no photo matches (the capture tests; here, not in a
    ``tests/capture/conftest.py``, whose module name ``conftest`` would shadow this file's for ``from conftest
    import ROOT`` in every folder collected after it)."""
    import shutil

    import numpy as np

    from omnirecon.data.io import write_image

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


def viewer_scene(tmp_path_factory, name: str):
    """The browser tests' start: skip without the shipped omnirecon-tiny or the viewer's three.js (fail under CI),
    then a procedural scene at 64 px with 8 views in a new folder. ``(folder, scene path, loaded scene)``"""
    from omnirecon.data.synth.generate import SynthOptions, generate_scene
    from omnirecon.engine.scenes import load_at_resolution
    from omnirecon.viewer.bundle import three_unavailable_reason

    if not (ROOT / "checkpoints" / "omnirecon-tiny" / "meta.json").is_file():
        pytest.skip("the shipped omnirecon-tiny checkpoint is not in this clone")
    require(three_unavailable_reason() is None, str(three_unavailable_reason()))
    tmp = tmp_path_factory.mktemp(name)
    scene_path = generate_scene(tmp / "scenes", 0, SynthOptions(resolution=64, views=8))
    return tmp, scene_path, load_at_resolution(scene_path, 64)


def procedural_photos(root: Path, resolution: int, views: int = 12) -> Path:
    """``root/photos``: the views of a procedural frontal scene (seed 0) as a folder of a user's photos, no poses
    (the scene itself is generated in ``root/synth``)."""
    import shutil

    from omnirecon.data import load_scene
    from omnirecon.data.synth.generate import SynthOptions, generate_scene

    ref = generate_scene(root / "synth", 0, SynthOptions(rig="frontal", views=views, resolution=resolution))
    out = root / "photos"
    out.mkdir()
    for name in load_scene(ref).names:
        shutil.copyfile(ref / name, out / Path(name).name)
    return out


def pytest_collection_modifyitems(config, items):
    """Tests marked ``slow`` first (collection order otherwise), so that under ``pytest -n 2`` (Makefile's test target)
    the workers' last tests are short ones and the two finish together."""
    items.sort(key=lambda item: not item.get_closest_marker("slow"))
