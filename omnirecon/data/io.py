"""File helpers shared by readers and writers: every failure becomes a one-line InputError."""

from __future__ import annotations

import json
import os
import tempfile
import tokenize
import zipfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from omnirecon.errors import InputError


def read_image(path: Path, mode: str | None = None, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image as float32 in [0, 1], ``# [H, W, C]`` (C = 1, 3 or 4; ``mode`` forces one).

    ``size = (width, height)`` resizes with area averaging (alpha premultiplied first) when the
    file's size differs.
    """
    from omnirecon.data.photo import open_photo, to_float

    path = Path(path)
    with open_photo(path) as im:  # regular file, claimed size checked, decoding errors named
        im.load()
        if size is not None and im.size != tuple(size):
            if im.mode not in ("L", "RGB", "RGBA"):
                from omnirecon.data.photo import to_8bit

                im = to_8bit(im)
            im = _resize(im, size)
        return to_float(im, mode)


def _resize(im, size):
    from PIL import Image

    if im.mode == "RGBA":  # premultiply so that transparent pixels do not bleed colour
        im = im.convert("RGBa").resize(size, Image.BOX).convert("RGBA")
        return im
    return im.resize(size, Image.BOX if im.mode in ("RGB", "L") else Image.NEAREST)


def read_json(path: Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise InputError("file is missing", path, "check the path (or the scene's --format)")
    try:
        return json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as e:  # JSONDecodeError, and ints over Python's digit limit
        raise InputError(f"invalid JSON ({str(e)[:160]})", path, "fix or regenerate the file") from e
    except RecursionError:
        raise InputError("JSON nested too deeply to read", path, "fix or regenerate the file") from None


def _check_npy_header(path: Path) -> None:
    """InputError when a ``.npy`` header claims more data than the file holds (a header claiming 10^13 rows
    would otherwise make NumPy try to allocate it) or a shape that is not a tuple of sizes."""
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            read = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
            shape, _, dtype = read.get(version, np.lib.format.read_array_header_2_0)(f, max_header_size=10_000)
            offset = f.tell()
    except (ValueError, OSError, EOFError, SyntaxError, tokenize.TokenError, TypeError) as e:
        raise InputError(f"cannot read NumPy file ({e})", path, "the file is corrupt; regenerate it") from None
    count = 1
    for n in shape:
        count *= int(n)
    need = count * max(dtype.itemsize, 1)
    have = path.stat().st_size - offset
    if dtype.hasobject or need > have:
        raise InputError(f"header claims shape {tuple(shape)} ({need:,} bytes) but the file holds {have:,} bytes",
                         path, "the file is truncated or corrupt; regenerate it")


def read_npy(path: Path, allow_pickle: bool = False):
    path = Path(path)
    if not path.is_file():
        raise InputError("file is missing", path, "check the path (or the scene's --format)")
    if path.suffix == ".npy":
        _check_npy_header(path)
    try:
        return np.load(path, allow_pickle=allow_pickle)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, SyntaxError, tokenize.TokenError,
            NotImplementedError, RuntimeError) as e:  # corrupt header or archive
        raise InputError(f"cannot read NumPy file ({e})", path, "the file is corrupt; regenerate it") from e


def list_images(folder: Path) -> list[Path]:
    """Image files in ``folder`` in sorted filename order."""
    exts = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".exr", ".webp"}
    return sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in exts and not p.name.startswith("."))


@contextmanager
def atomic_path(path: Path):
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds. The name
    carries our PID, so :func:`omnirecon.outputs.clean_stale` can remove it after a crash."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.pid{os.getpid()}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file the usual permissions
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_json(path: Path, obj) -> None:
    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(obj, indent=1))


def write_image(path: Path, array: np.ndarray) -> None:
    """Write ``# [H, W, C]`` float in [0, 1] (or uint8/uint16) as PNG/JPEG, atomically."""
    from PIL import Image

    a = np.asarray(array)
    if a.dtype != np.uint8 and a.dtype != np.uint16:
        a = (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    with atomic_path(path) as tmp:
        Image.fromarray(a).save(tmp, format=Path(path).suffix.lstrip(".").upper().replace("JPG", "JPEG"))
