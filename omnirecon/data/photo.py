"""Photos as they come: every image the tool reads (scene readers, masks, ``process``'s photo folder) is
opened here.

* Only regular files are opened: a FIFO would block the run forever and a device (``/dev/zero``) never
  ends; both are refused by :func:`regular_file` before any ``open``.
* The size the header claims is checked before any pixel is decoded (:func:`open_photo`): at most
  :data:`MAX_PIXELS`, and the decoded image must fit in the memory available now. A PNG that claims
  100,000 x 100,000 pixels in a few hundred bytes (a decompression bomb) is refused by name; Pillow's own
  bomb warning never reaches stderr.
* Every pixel format becomes float32 in [0, 1] with its true range (:func:`to_float`): 8-bit, 16-bit
  (``I;16`` PNGs, which ``Image.convert("RGB")`` would clip to white), 32-bit integer and float
  greyscale, palette (with its transparency), CMYK, YCbCr, 1-bit, with or without alpha.
* EXIF orientation: :func:`upright` turns a photo upright, as ``process`` stages it for COLMAP. Scene
  readers keep the stored pixel order on purpose: a scene's poses and intrinsics were computed on it.
"""

from __future__ import annotations

import os
import re
import stat
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from omnirecon.errors import InputError
from omnirecon.memory import memory_bytes

MAX_PIXELS = 178_000_000
"""Largest image accepted (width x height): 178 MP, above any camera's photo and below Pillow's own bomb
error (2 x ``Image.MAX_IMAGE_PIXELS``), so a file Pillow refuses is always over this limit too."""
DECODED_BYTES_PER_PIXEL = 16
"""Decoding plus the float32 RGBA copy (4 x 4 bytes per pixel)."""
BROKEN = (OSError, ValueError, SyntaxError, EOFError, IndexError, KeyError, TypeError, ZeroDivisionError,
          MemoryError)
"""Exceptions Pillow raises on corrupt files (the plugins are not uniform)."""


def regular_file(path: Path, what: str = "image file", fix: str = "point at a regular image file") -> Path:
    """``path`` when it is a regular file (or a link to one); InputError naming it otherwise."""
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputError(f"{what} is missing", path, "check the path, or remove the view from the pose file") from None
    except OSError as e:
        raise InputError(f"cannot read the {what} ({e.strerror})", path, "check the path and its permissions") from None
    if stat.S_ISREG(st.st_mode):
        return path
    kind = ("a folder" if stat.S_ISDIR(st.st_mode) else "a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode)
            else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
            else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
    raise InputError(f"the {what} is {kind}, not a regular file", path, fix)


def check_claimed_size(width: int, height: int, path: Path) -> None:
    """InputError when a header's ``width x height`` is empty, above :data:`MAX_PIXELS`, or would not fit in
    half the memory available now once decoded."""
    pixels = int(width) * int(height)
    if pixels <= 0:
        raise InputError(f"image header claims {width}x{height} pixels", path, "the file is corrupt; replace it")
    available = memory_bytes()[1]
    if pixels > MAX_PIXELS or pixels * DECODED_BYTES_PER_PIXEL > available / 2:
        raise InputError(f"image header claims {width}x{height} pixels ({pixels / 1e6:.0f} MP; limit "
                         f"{min(MAX_PIXELS, available / 2 / DECODED_BYTES_PER_PIXEL) / 1e6:.0f} MP here), "
                         "a decompression bomb or a damaged file", path, "resize the image or replace the file")


@contextmanager
def open_photo(path: Path, what: str = "image file"):
    """A Pillow image of ``path`` with its header checked (regular file, claimed size); decoding errors,
    Pillow's bomb errors and warnings become one InputError naming the file."""
    from PIL import Image, UnidentifiedImageError

    path = regular_file(path, what)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Pillow's DecompressionBombWarning: our own check applies
            im = Image.open(path)
        with im:
            check_claimed_size(*im.size, path)
            yield im
    except InputError:
        raise
    except Image.DecompressionBombError as e:  # over 2x Pillow's limit, so over ours: the header's claim
        claimed = re.search(r"\((\d+) pixels\)", str(e))
        raise InputError(f"image header claims {int(claimed.group(1)) / 1e6 if claimed else 0:.0f} MP (limit "
                         f"{MAX_PIXELS / 1e6:.0f} MP), a decompression bomb or a damaged file", path,
                         "resize the image or replace the file") from None
    except (UnidentifiedImageError, *BROKEN) as e:
        detail = str(e).replace(str(path), "").replace("''", "").strip(" :")[:120]
        raise InputError(f"cannot read {what} ({type(e).__name__}{': ' + detail if detail else ''})", path,
                         "the file is corrupt or not an image; replace it") from e


def upright(im):
    """``im`` turned upright by its EXIF orientation (a copy), and the orientation tag it had."""
    from PIL import ImageOps

    orientation = im.getexif().get(0x0112, 1)
    return ImageOps.exif_transpose(im), orientation


def to_float(im, mode: str | None = None) -> np.ndarray:
    """float32 pixels in [0, 1], ``# [H, W, C]``: C = 1 (grey), 3 (RGB) or 4 (RGBA), or forced by ``mode``
    (``L``, ``RGB`` or ``RGBA``; ``I``: stored integers / 65535, for depth and label maps). High bit depths keep their range (16-bit divides by 65535)."""
    high = im.mode in ("I;16", "I;16L", "I;16B", "I;16N", "I", "F")
    if mode == "I":  # integer maps (depth, labels): the stored integers / 65535, whatever the bit depth
        ints = im if high and im.mode != "F" else im.convert("I")
        return (np.asarray(ints).astype(np.float64) / 65535.0).astype(np.float32)[..., None]
    if high:
        arr = np.asarray(im)
        if arr.dtype.kind == "f":
            grey = np.nan_to_num(arr.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
            grey = grey / 65535.0 if grey.max(initial=0) > 1.0 else grey
        else:
            grey = arr.astype(np.float32) / 65535.0
        out = np.clip(grey, 0.0, 1.0)[..., None]  # [H, W, 1]
        if mode in ("RGB", "RGBA"):
            out = np.repeat(out, 3, axis=-1)
            if mode == "RGBA":
                out = np.concatenate([out, np.ones_like(out[..., :1])], axis=-1)
        return np.ascontiguousarray(out)
    if im.mode == "P":
        im = im.convert("RGBA" if "transparency" in im.info else "RGB")
    if mode is not None and im.mode != mode:
        im = im.convert(mode)
    elif im.mode not in ("L", "RGB", "RGBA"):
        im = im.convert("RGBA" if "A" in im.mode or "transparency" in im.info else
                        "L" if im.mode in ("1", "L") else "RGB")
    out = np.asarray(im).astype(np.float32) / 255.0
    return out[..., None] if out.ndim == 2 else out


def to_8bit(im):
    """``im`` as an 8-bit ``L``, ``RGB`` or ``RGBA`` Pillow image with its true range (16-bit scaled, not
    clipped): what COLMAP and PNG writers read."""
    from PIL import Image

    if im.mode in ("L", "RGB", "RGBA"):
        return im
    if im.mode in ("I;16", "I;16L", "I;16B", "I;16N", "I", "F"):
        return Image.fromarray(np.round(to_float(im)[..., 0] * 255).astype(np.uint8), "L")
    if im.mode == "P":
        return im.convert("RGBA" if "transparency" in im.info else "RGB")
    return im.convert("RGBA" if "A" in im.mode else "L" if im.mode == "1" else "RGB")
