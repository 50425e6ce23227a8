"""``photos``: scenes of three formats and a photo folder for ``process`` whose images are decompression bombs,
truncated, empty, FIFOs, devices, folders or links to them; and ``photos_valid``: unusual *valid* photos (16-bit,
palette, CMYK, grey + alpha), which must be *accepted* (exit 0, no traceback)."""

from __future__ import annotations

import os
import shutil
import struct
import zlib
from pathlib import Path


def _png_bomb(path: Path, w: int, h: int) -> None:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\0" * 4096)) + chunk(b"IEND", b""))


def _bad_image(path: Path, kind: str) -> None:
    """Replace the image at ``path`` by a hostile one of ``kind``."""
    if path.exists() or path.is_symlink():
        path.unlink()
    if kind.startswith("bomb"):
        side = {"bomb_wide": (2**31 - 1, 1), "bomb_tall": (1, 2**31 - 1), "bomb": (100_000, 100_000),
                "bomb_mid": (20_000, 20_000)}[kind]
        _png_bomb(path, *side)
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated_header":
        path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\x0dIHDR")
    elif kind == "jpeg_header":
        path.write_bytes(b"\xff\xd8\xff\xe0\x00\x10JFIF\x00")
    elif kind == "zero_size":
        _png_bomb(path, 0, 0)
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "dev_zero":
        os.symlink("/dev/zero", path)
    elif kind == "dev_null":
        os.symlink("/dev/null", path)
    elif kind == "folder":
        path.mkdir()
    elif kind == "self_link":
        os.symlink(path.name, path)
    elif kind == "text":
        path.write_text("this is text, not a picture\n" * 20)
    else:
        raise ValueError(kind)


BAD_IMAGES = ["bomb", "bomb_wide", "bomb_tall", "bomb_mid", "empty", "truncated_header", "jpeg_header",
              "zero_size", "fifo", "dev_zero", "dev_null", "folder", "self_link", "text"]
GOOD_MODES = ["I;16", "P", "PA", "CMYK", "LA", "RGBA", "1", "L"]


def _good_image(path: Path, mode: str, seed: int) -> Path:
    import numpy as np
    from PIL import Image

    rng = np.random.default_rng(seed)
    if mode in ("I;16", "I"):
        im = Image.fromarray((rng.random((8, 8)) * 65535).astype(np.uint16))
        im = im if mode == "I;16" else im.convert("I")
    else:
        im = Image.fromarray((rng.random((8, 8, 3)) * 255).astype(np.uint8)).convert(mode)
    target = path.with_suffix(".tif") if mode in ("CMYK", "PA") else path
    im.save(target)
    return target



def photo_cases(p: dict[str, Path], work: Path) -> list[dict]:
    """One image of a scene (blender, llff, colmap) or of the photo folder made hostile in each way; and every image
    of the blender scene / the photo folder in an unusual valid mode."""
    C, O, tiny = str(p["ck"]), "{out}", ["--threads", "1"]
    out: list[dict] = []
    targets = {"blender": (p["scene"], "train/r_1.png"), "llff": (p["llff"], "images/img_001.png"),
               "colmap": (p["colmap"], "images/im1.png"), "photos": (p["photos"], "p1.png")}
    for fmt, (scene, rel) in targets.items():
        for kind in BAD_IMAGES:
            d = work / "photos_cases" / f"{fmt}_{kind}"
            shutil.copytree(scene, d, symlinks=True)
            _bad_image(d / rel, kind)
            cmd = ["process", str(d), "--out", O] if fmt == "photos" else ["inspect", str(d), "--out", O]
            out.append({"class": "photos", "args": cmd, "named": str(d / rel)})
            if fmt == "blender" and kind in ("bomb", "fifo", "dev_zero", "truncated_header"):
                for verb in (["render", "--scene", str(d), "--ckpt", C, "--out", O, "--no-video", *tiny],
                             ["mesh", "--scene", str(d), "--model", "floor", "--out", O + ".ply", *tiny],
                             ["train", "--data", str(d), "--out", O, "--model", "gpnr-tiny", "--steps", "1", *tiny]):
                    out.append({"class": "photos", "args": verb, "named": str(d / rel)})
        if fmt in ("blender", "photos"):
            out += _valid_cases(fmt, scene, rel, work)
    return out


def _valid_cases(fmt: str, scene: Path, rel: str, work: Path) -> list[dict]:
    """``photos_valid``: the photo folder with every photo in each of GOOD_MODES (staged, not refused), or the blender
    scene with its image ``rel`` in each mode the blender reader finds (a .png)."""
    out = []
    for i, mode in enumerate(GOOD_MODES):
        d = work / "photos_cases" / f"{fmt}_good_{mode.replace(';', '')}"
        shutil.copytree(scene, d, symlinks=True)
        if fmt == "photos":  # every photo in this mode (distinct content): must be staged, not refused
            for j in range(4):
                (d / f"p{j}.png").unlink()
                _good_image(d / f"p{j}.png", mode, seed=10 * i + j)
            out.append({"class": "photos_valid", "args": ["inspect_photos", str(d)], "named": None, "accept": True})
        else:
            (d / rel).unlink()
            made = _good_image(d / rel, mode, seed=i)
            if made != d / rel:
                continue  # the blender reader looks for .png
            out.append({"class": "photos_valid", "args": ["inspect", str(d), "--out", "{out}"], "named": None,
                        "accept": True})
    return out
