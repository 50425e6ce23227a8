"""Where the shipped checkpoints are, in a source checkout and in an installed wheel alike.

The tiny checkpoints (``omnirecon-tiny``, ``gpnr-tiny``, ``ibrnet-tiny``) are package data: the folder
``omnirecon/_checkpoints`` is a link to the repository's ``checkpoints/`` in a source checkout, and the wheel
holds copies of ``checkpoints/*-tiny`` there (pyproject.toml, ``[tool.setuptools.package-data]``), so
``importlib.resources`` finds them wherever the package is installed. :func:`checkpoint_folder` is the one
place a ``--ckpt`` value becomes a folder: a path that exists is taken as it is, and a shipped name (``omnirecon-tiny``,
or the checkout-relative ``checkpoints/omnirecon-tiny`` the docs use) is found here from any working folder.
Checkpoints written by ``omnirecon train --out checkpoints/...`` are ordinary paths and stay where they are.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

SHIPPED_FOLDER = "_checkpoints"
"""The package-data folder of the shipped checkpoints inside the ``omnirecon`` package."""


def shipped_folder() -> Path:
    """The folder holding the shipped checkpoints, one sub-folder per name (real path: the checkout's
    ``checkpoints/`` when the package runs from a source checkout)."""
    return Path(str(resources.files("omnirecon").joinpath(SHIPPED_FOLDER))).resolve()


def shipped_checkpoint(name: str) -> Path:
    """The folder of the shipped checkpoint ``name`` (e.g. ``"omnirecon-tiny"``); it may be missing in a clone
    without the weights, and callers check ``meta.json`` as for any checkpoint."""
    return shipped_folder() / name


def checkpoint_folder(ckpt: str | Path) -> Path:
    """The checkpoint folder a ``--ckpt`` value names: ``ckpt`` itself when it exists; else, for a relative
    ``NAME`` or ``checkpoints/NAME`` whose shipped checkpoint exists, that one; else ``ckpt`` unchanged (so the
    caller's error names what the user typed)."""
    path = Path(ckpt)
    if path.exists() or path.is_absolute() or len(path.parts) > 2:
        return path
    if len(path.parts) == 2 and path.parts[0] != "checkpoints":
        return path
    shipped = shipped_checkpoint(path.name)
    return shipped if (shipped / "meta.json").is_file() else path
