"""Photos as they come (omnirecon/data/photo.py): every pixel format with its true range, EXIF orientation
when staging, header sizes and non-regular files refused before decoding."""

from __future__ import annotations

import os

import numpy as np
import pytest
from PIL import Image

from omnirecon.capture.images import stage_images
from omnirecon.data.io import read_image
from omnirecon.errors import InputError

RNG = np.random.default_rng(0)
GREY16 = (RNG.random((12, 16)) * 65535).astype(np.uint16)  # [H, W]


def test_16_bit_grey_keeps_its_range(tmp_path):
    Image.fromarray(GREY16).save(tmp_path / "g.png")
    assert Image.open(tmp_path / "g.png").mode.startswith("I")
    for mode in (None, "L", "RGB", "RGBA"):
        a = read_image(tmp_path / "g.png", mode=mode)
        assert np.allclose(a[..., 0], GREY16 / 65535.0, atol=1e-6), mode  # not clipped to white
    assert read_image(tmp_path / "g.png", mode="RGB").shape == (12, 16, 3)


@pytest.mark.parametrize("mode", ["P", "PA", "CMYK", "LA", "1", "YCbCr", "I", "F"])
def test_every_mode_reads_as_rgb_in_range(tmp_path, mode):
    rgb = (RNG.random((12, 16, 3)) * 255).astype(np.uint8)
    im = Image.fromarray(rgb).convert(mode)
    path = tmp_path / ("x.tif" if mode in ("CMYK", "YCbCr", "I", "F", "PA") else "x.png")
    im.save(path)
    a = read_image(path, mode="RGB")
    assert a.shape == (12, 16, 3) and a.dtype == np.float32 and 0 <= a.min() and a.max() <= 1 and a.std() > 0


def test_palette_transparency_becomes_alpha(tmp_path):
    im = Image.fromarray((RNG.random((8, 8)) * 4).astype(np.uint8), "P")
    im.putpalette([0, 0, 0, 255, 0, 0, 0, 255, 0, 0, 0, 255] + [0] * 756)
    im.info["transparency"] = 0
    im.save(tmp_path / "p.png", transparency=0)
    a = read_image(tmp_path / "p.png")
    assert a.shape[-1] == 4 and set(np.unique(a[..., 3])) <= {0.0, 1.0}


def test_header_bombs_fifos_and_devices_are_refused(tmp_path):
    big = Image.new("L", (1, 1))
    big.save(tmp_path / "ok.png")
    raw = bytearray((tmp_path / "ok.png").read_bytes())
    import struct
    import zlib
    raw[16:24] = struct.pack(">II", 100_000, 100_000)  # IHDR width/height
    raw[29:33] = struct.pack(">I", zlib.crc32(bytes(raw[12:29])))
    (tmp_path / "bomb.png").write_bytes(bytes(raw))
    with pytest.raises(InputError, match="header claims .* decompression bomb"):
        read_image(tmp_path / "bomb.png")
    os.mkfifo(tmp_path / "fifo.png")
    with pytest.raises(InputError, match="FIFO"):
        read_image(tmp_path / "fifo.png")  # would block forever if opened
    with pytest.raises(InputError, match="device"):
        read_image("/dev/zero")


def test_staging_16_bit_grey_photos_and_exif(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):  # valid 16-bit greyscale photos: distinct, not "identical"
        Image.fromarray((RNG.random((12, 16)) * 65535).astype(np.uint16)).save(photos / f"g{i}.png")
    staged = stage_images(photos, tmp_path / "st")
    means = [np.asarray(Image.open(staged.folder / n)).mean() for n in staged.names]
    assert all(100 < m < 160 for m in means), means  # mid-grey, not white
    rgb = Image.fromarray((RNG.random((12, 16, 3)) * 255).astype(np.uint8))
    exif = rgb.getexif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise to be upright
    rgb.save(photos / "turned.jpg", exif=exif)
    staged = stage_images(photos, tmp_path / "st2", shared_camera=False)
    assert staged.sizes["turned.png"] == (12, 16) and staged.rotated == 1
