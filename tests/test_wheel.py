"""The package outside the checkout: a wheel built from this tree, installed on its own, runs ``reconstruct`` with
the checkpoint it carries, from a working folder that is not the checkout (issue 45, item 6)."""

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from conftest import ROOT, require

from omnirecon.engine.shipped import checkpoint_folder, shipped_checkpoint, shipped_folder


def test_a_shipped_name_is_found_from_any_working_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    tiny = shipped_checkpoint("omnirecon-tiny")
    if not (tiny / "meta.json").is_file():
        pytest.skip("the shipped omnirecon-tiny checkpoint is not in this clone")
    assert tiny.parent == shipped_folder() and tiny.is_absolute()
    assert checkpoint_folder("omnirecon-tiny") == tiny
    assert checkpoint_folder(Path("checkpoints") / "omnirecon-tiny") == tiny  # the docs' checkout-relative spelling
    assert checkpoint_folder("elsewhere/omnirecon-tiny") == Path("elsewhere/omnirecon-tiny")  # not a shipped name
    assert checkpoint_folder("no-such-tiny") == Path("no-such-tiny")  # the caller's error names what was typed
    (tmp_path / "checkpoints" / "omnirecon-tiny").mkdir(parents=True)  # a folder that exists wins (train --out)
    assert checkpoint_folder("checkpoints/omnirecon-tiny") == Path("checkpoints/omnirecon-tiny")


def _source_copy(dest: Path) -> Path:
    """The files a wheel is built from (package, shipped checkpoints, pyproject, README), copied so the build's
    ``build/`` and ``*.egg-info`` never land in the checkout; ``omnirecon/_checkpoints`` stays a link."""
    dest.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, dest / name)
    shutil.copytree(ROOT / "omnirecon", dest / "omnirecon", symlinks=True,
                    ignore=shutil.ignore_patterns("node_modules", "__pycache__", "*.egg-info"))
    shutil.copytree(ROOT / "checkpoints", dest / "checkpoints", ignore=shutil.ignore_patterns("runs"))
    return dest


def _pip(*args: str, cwd: Path) -> None:
    done = subprocess.run([sys.executable, "-m", "pip", *args, "--no-deps", "--no-index", "-q"], cwd=cwd,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]


@pytest.mark.slow
def test_the_installed_wheel_reconstructs_outside_the_checkout(tmp_path):
    """Build the wheel (no network: this environment's setuptools), ``pip install --target`` it, then from a
    folder outside the checkout, with only the installed copy on ``PYTHONPATH``: ``omnirecon synth`` a tiny
    scene and ``omnirecon reconstruct`` it with the default checkpoint, which must be the wheel's own."""
    require(importlib.util.find_spec("setuptools") is not None, "building the wheel needs setuptools (pip install setuptools)")
    if not (ROOT / "checkpoints" / "omnirecon-tiny" / "meta.json").is_file():
        pytest.skip("the shipped omnirecon-tiny checkpoint is not in this clone")
    src = _source_copy(tmp_path / "src")
    _pip("wheel", "--no-build-isolation", "-w", str(tmp_path / "dist"), str(src), cwd=tmp_path)
    (wheel,) = (tmp_path / "dist").glob("omnirecon-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
    for model in ("omnirecon-tiny", "gpnr-tiny", "ibrnet-tiny"):
        assert {f"omnirecon/_checkpoints/{model}/{f}" for f in ("meta.json", "model.safetensors")} <= names, model
    assert not any("/runs/" in n for n in names)  # training runs stay in the checkout
    for sized in (ROOT / "checkpoints").glob("*-tiny/sizes/*/model.safetensors"):  # weights at other image sizes
        assert f"omnirecon/_checkpoints/{sized.relative_to(ROOT / 'checkpoints')}" in names, sized
    site = tmp_path / "site"
    _pip("install", "--target", str(site), str(wheel), cwd=tmp_path)
    work = tmp_path / "work"  # outside the checkout: nothing relative to the cwd resolves into it
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}
    omnirecon = [str(site / "bin" / "omnirecon")]
    for args in (["synth", "--out", "scenes", "--views", "8", "--resolution", "32"],
                 ["reconstruct", "scenes/scene_00000", "--out", "rec", "--resolution", "32", "--mesh-resolution", "32",
                  "--finetune-seconds", "0", "--frames", "2", "--no-viewer", "--threads", "1"]):
        done = subprocess.run(omnirecon + args, cwd=work, env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr[-2000:]
    record = json.loads((work / "rec" / "reconstruct.json").read_text())
    used = Path(record["checkpoint"])
    assert used.is_relative_to(site.resolve()) and used.name == "omnirecon-tiny", used  # the wheel's, not the checkout's
    assert (work / "rec" / "index.html").is_file() and (work / "rec" / "mesh.ply").stat().st_size > 1000
