"""``folders_valid``: photo folders of mixed sizes, CMYK / grey JPEG, 16-bit PNG, EXIF-rotated, WebP, BMP, TIFF
(staged); ``folders``: a truncated JPEG / PNG, a JPEG claiming 65000 px sides, a link loop, a file reading fails on,
HEIC, an animated GIF, a folder linking to itself, none / one / two photos (refused)."""

from __future__ import annotations

import os
import struct
from pathlib import Path

from bench.hostile.fixtures import exif_rotated, photo, photo16


def valid_folder_cases(work: Path) -> list[dict]:
    """``folders_valid``: photo folders a user's devices write (mixed sizes, CMYK JPEG, 16-bit colour and grey PNG,
    grey JPEG, EXIF-rotated JPEG, upper-case extensions, WebP, BMP, TIFF): staged as `process` stages them."""
    makers = {
        "mixed_sizes": lambda d, i: photo(d / f"p{i}.jpg", i, size=(40 + 8 * i, 30 + 4 * i)),
        "cmyk_jpeg": lambda d, i: photo(d / f"p{i}.jpg", i, mode="CMYK", format="JPEG"),
        "rgb16_png": lambda d, i: photo16(d / f"p{i}.png", i, 3),
        "grey16_png": lambda d, i: photo16(d / f"p{i}.png", i, 1),
        "grey_jpeg": lambda d, i: photo(d / f"p{i}.jpg", i, mode="L", format="JPEG"),
        "exif_rotated": lambda d, i: exif_rotated(d / f"p{i}.jpg", i),
        "upper_ext": lambda d, i: photo(d / f"P{i}.JPG", i, format="JPEG"),
        "webp": lambda d, i: photo(d / f"p{i}.webp", i, format="WEBP"),
        "bmp": lambda d, i: photo(d / f"p{i}.bmp", i, format="BMP"),
        "jpeg_named_png": lambda d, i: photo(d / f"p{i}.png", i, format="JPEG"),
        "mixed_formats": lambda d, i: photo(d / f"p{i}.{('jpg', 'png', 'webp', 'tif')[i]}", i,
                                             format=("JPEG", "PNG", "WEBP", "TIFF")[i]),
    }
    out = []
    for name, make in makers.items():
        d = work / "folders" / f"valid_{name}"
        for i in range(4):
            make(d, i)
        out.append({"class": "folders_valid", "args": ["inspect_photos", str(d), *["per_image"] * (name == "mixed_sizes")],
                    "named": None, "accept": True})
    d = work / "folders" / "valid_mixed_sizes"  # one camera model for all: refused, naming the photo and the option
    out.append({"class": "folders_valid", "args": ["process", str(d), "--out", "{out}", "--threads", "1"],
                "named": "--per-image-cameras"})
    return out


def _hostile_member(d: Path, kind: str) -> Path:
    """Put a hostile member into the photo folder ``d``; the path the error must name."""
    good = (d / "p0.jpg").read_bytes()
    bad = d / "p9.jpg"
    if kind == "truncated_jpeg":
        bad.write_bytes(good[: len(good) // 2])
    elif kind == "truncated_png":
        photo(d / "p9.png", 9, format="PNG")
        bad = d / "p9.png"
        bad.write_bytes(bad.read_bytes()[:-40])
    elif kind == "jpeg_bomb":  # a SOF0 frame header claiming 65000 x 65000
        i = good.index(b"\xff\xc0")
        bad.write_bytes(good[: i + 5] + struct.pack(">HH", 65000, 65000) + good[i + 9:])
    elif kind == "link_loop":
        os.symlink("p8.jpg", bad)
        os.symlink("p9.jpg", d / "p8.jpg")
    elif kind == "unreadable":  # reading it fails (EIO), as an unreadable file does for a user without the right
        os.symlink("/proc/self/mem", bad)
    elif kind == "heic":
        bad = d / "p9.heic"
        bad.write_bytes(b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic" + os.urandom(200))
    elif kind == "gif_animated":
        from PIL import Image

        bad = d / "p9.gif"
        frames = [Image.open(d / f"p{i}.jpg").convert("P") for i in range(2)]
        frames[0].save(bad, save_all=True, append_images=frames[1:])
        return bad
    elif kind == "zero_width_jpeg":
        i = good.index(b"\xff\xc0")
        bad.write_bytes(good[: i + 5] + struct.pack(">HH", 30, 0) + good[i + 9:])
    elif kind == "text_jpg":
        bad.write_text("a note, not a photo\n")
    else:
        raise ValueError(kind)
    return bad


def folder_cases(work: Path) -> list[dict]:
    """``folders``: photo folders with one hostile member (truncated JPEG / PNG, a JPEG claiming 65000 px sides, a link
    loop, a file reading fails on, HEIC, an animated GIF, a zero-width JPEG, text named .jpg), a folder linking to
    itself, an empty one, one photo: `process` and `reconstruct` refuse naming the member, leave nothing."""
    out = []
    tiny = ["--threads", "1", "--quiet"]
    for kind in ("truncated_jpeg", "truncated_png", "jpeg_bomb", "link_loop", "unreadable", "heic", "gif_animated",
                 "zero_width_jpeg", "text_jpg"):
        d = work / "folders" / kind
        for i in range(4):
            photo(d / f"p{i}.jpg", i, format="JPEG")
        bad = _hostile_member(d, kind)
        named = str(d) if kind == "link_loop" else str(bad)  # either link of the loop
        out.append({"class": "folders", "args": ["process", str(d), "--out", "{out}", *tiny], "named": named})
        out.append({"class": "folders", "args": ["reconstruct", str(d), "--out", "{out}", "--threads", "1",
                                                 "--no-viewer"], "named": named})
    d = work / "folders" / "dir_loop"
    for i in range(4):
        photo(d / f"p{i}.jpg", i, format="JPEG")
    os.symlink("..", d / "sub")
    out.append({"class": "folders", "args": ["process", str(d), "--out", "{out}", *tiny], "named": str(d)})
    for name, count in (("empty", 0), ("one_photo", 1), ("two_photos", 2)):
        d = work / "folders" / name
        d.mkdir(parents=True)
        for i in range(count):
            photo(d / f"p{i}.jpg", i, format="JPEG")
        for verb in ("process", "reconstruct"):
            out.append({"class": "folders", "args": [verb, str(d), "--out", "{out}", "--threads", "1"], "named": str(d)})
    return out

