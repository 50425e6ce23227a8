"""The hostile set's shared fixtures (a scene of each format, a checkpoint, a photo folder, a file, a dangling link)
and the photo makers the classes use; the command lines every numeric option is tried on."""

from __future__ import annotations

import os
from pathlib import Path


def build(root: Path) -> dict[str, Path]:
    """Every fixture the cases name, under ``root``."""

    from omnirecon.engine.checkpoint import save_checkpoint
    from omnirecon.models.registry import build_model
    from tests.data.test_bad_input import blender_scene, colmap_scene, llff_scene, tiny_image

    p: dict[str, Path] = {"root": root}
    p["scene"] = blender_scene(root / "scene")
    (p["scene"] / "transforms_test.json").write_text((p["scene"] / "transforms_train.json").read_text())
    p["llff"] = llff_scene(root / "llff")
    p["colmap"] = colmap_scene(root / "colmap")
    save_checkpoint(root / "ck", build_model("omnirecon-tiny", {"coarse_samples": 4, "fine_samples": 2,
                                                                 "volume_resolution": 8}), "omnirecon-tiny")
    p["ck"] = root / "ck"
    p["photos"] = root / "photos"
    for i in range(4):
        tiny_image(p["photos"] / f"p{i}.png", w=32, h=24, seed=i)
    p["a_file"] = root / "a_file.txt"
    p["a_file"].write_text("x")
    p["dangling"] = root / "dangling"
    os.symlink(root / "no" / "such", p["dangling"])
    return p



def base_commands(p: dict[str, Path]) -> dict[str, list[str]]:
    """``{verb: a command line that runs it on the fixtures}`` (``{out}``: the case's output path)."""
    S, C, O = str(p["scene"]), str(p["ck"]), "{out}"
    return {
        "demo": ["demo", "--out", O], "synth": ["synth", "--out", O], "process": ["process", str(p["photos"]), "--out", O],
        "inspect": ["inspect", S, "--out", O], "eval": ["eval", "--ckpt", C, "--scenes", S, "--out", O],
        "render": ["render", "--scene", S, "--ckpt", C, "--out", O, "--no-video"],
        "train": ["train", "--data", S, "--out", O, "--model", "gpnr-tiny", "--steps", "2"],
        "mesh": ["mesh", "--scene", S, "--model", "floor", "--out", O + ".ply"],
        "lift": ["lift", "--ckpt", C, "--scene", S, "--out", O], "edit": ["edit", "--ckpt", C, "--scene", S, "--out", O],
        "pet": ["pet", "--ckpt", C, "--scene", S, "--out", O], "finetune": ["finetune", "--ckpt", C, "--scene", S, "--out", O],
        "export": ["export", "--ckpt", C, "--scene", S, "--out", O], "view": ["view", S, "--no-browser"],
        "bench": ["bench", "--ckpt", C, "--out", O + ".json"], "reconstruct": ["reconstruct", S, "--out", O],
    }


def photo(path: Path, seed: int, size=(40, 30), mode="RGB", **save) -> Path:
    import numpy as np
    from PIL import Image

    im = Image.fromarray((np.random.default_rng(seed).random((size[1], size[0], 3)) * 255).astype(np.uint8))
    path.parent.mkdir(parents=True, exist_ok=True)
    im.convert(mode).save(path, **save)
    return path


def photo16(path: Path, seed: int, channels: int) -> Path:
    import cv2
    import numpy as np

    a = (np.random.default_rng(seed).random((30, 40, channels)) * 65535).astype(np.uint16)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), a if channels > 1 else a[..., 0])
    return path


def exif_rotated(path: Path, seed: int) -> Path:
    from PIL import Image

    photo(path, seed, format="JPEG")
    im = Image.open(path)
    exif = im.getexif()
    exif[0x0112] = 6  # rotate 90 degrees on display
    im.save(path, format="JPEG", exif=exif)
    return path

