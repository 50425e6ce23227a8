"""A folder of photos, checked and staged for structure from motion.

:func:`stage_images` reads every file of the folder once and raises :class:`InputError` (naming the
file and the fix) for: a missing or empty folder, no images, fewer than ``min_images``, a file that is
not a decodable image, all images identical, or different sizes under one shared camera. It writes
what COLMAP reads into ``dest``: the file itself (hard link or copy) when it is an upright JPEG or
PNG, otherwise the pixels turned upright by their EXIF orientation (``ImageOps.exif_transpose``) and
saved as PNG. Hidden files (``.DS_Store``) and sub-folders are skipped.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from PIL import ImageFilter

from omnirecon.data.photo import open_photo, regular_file, to_8bit, upright
from omnirecon.errors import InputError

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
VIDEO_EXTS = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".gif")
EXIF_ORIENTATION = 0x0112


@dataclass
class StagedImages:
    """Images ready for COLMAP."""

    folder: Path
    """Folder holding the staged files."""
    names: list[str]
    """File names in ``folder``, sorted (the order of a video's frames)."""
    sources: dict[str, Path]
    """Original file of each staged name."""
    sizes: dict[str, tuple[int, int]]
    """``(width, height)`` of each staged image (after EXIF orientation)."""
    rotated: int = 0
    """How many images were turned upright by their EXIF orientation."""


def _visible_files(folder: Path) -> list[Path]:
    """Visible entries of ``folder`` but sub-folders; a FIFO, device or socket among them is refused (opening
    one would block or never end)."""
    for p in folder.iterdir():
        if p.is_dir() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_EXTS:
            raise InputError("a folder named like a photo", p, "move it out of the photo folder")
    files = sorted(p for p in folder.iterdir() if not p.name.startswith(".") and not p.is_dir())
    for p in files:
        regular_file(p, "file in the photo folder", "move it out of the photo folder")
    return files


def count_files(folder: Path) -> int | None:
    """Visible files in ``folder`` (what :func:`stage_images` reads), or None when it is not a folder."""
    folder = Path(folder)
    return len(_visible_files(folder)) if folder.is_dir() else None


def stage_images(folder: Path, dest: Path, min_images: int = 3, shared_camera: bool = True,
                 on_file=None) -> StagedImages:
    """Check the photos in ``folder`` and stage them into ``dest`` (see the module docstring).
    ``on_file()`` is called after each file is read."""

    folder = Path(folder)
    if not folder.exists():
        raise InputError("input does not exist", folder, "pass a folder of photos or a video file")
    files = _visible_files(folder)
    if not files:
        raise InputError("the folder is empty", folder, "put the photos (JPEG or PNG) in it")
    videos = [p for p in files if p.suffix.lower() in VIDEO_EXTS]
    others = [p for p in files if p.suffix.lower() not in IMAGE_EXTS and p not in videos]
    if not [p for p in files if p.suffix.lower() in IMAGE_EXTS]:
        hint = f"pass the video itself: omnirecon process {videos[0]}" if videos else "put the photos (JPEG or PNG) in it"
        raise InputError(f"no images in the folder ({len(files)} other file{'s' * (len(files) != 1)})", folder, hint)
    if others:
        raise InputError(f"not an image file ({len(others)} such file{'s' * (len(others) != 1)} in the folder)",
                         others[0], "move non-image files out of the photo folder")
    if videos:
        raise InputError("a video among the photos", videos[0], "process the photos and the video separately")

    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    names, sources, sizes, digests, rotated = [], {}, {}, set(), 0
    for p in files:
        with open_photo(p) as im:  # regular file, claimed size checked; decoding errors name the file
            im.load()
            up, orientation = upright(im)
            fmt, mode = im.format, up.mode
            up = to_8bit(up)  # 16-bit, palette, CMYK...: 8-bit with their true range
            digests.add(hashlib.sha1(up.tobytes() + repr(up.size).encode()).hexdigest())
            copy_as_is = orientation in (None, 1) and fmt in ("JPEG", "PNG") and mode in ("RGB", "RGBA", "L")
            name = p.name if copy_as_is or p.suffix.lower() == ".png" else p.stem + ".png"
            if name in sources:
                raise InputError(f"two photos would both be staged as {name}", p, "rename one of them")
            target = dest / name
            if copy_as_is:
                try:
                    os.link(p, target)
                except OSError:
                    shutil.copyfile(p, target)
            else:
                up.save(target)
                rotated += orientation not in (None, 1)
            sizes[name] = up.size
        names.append(name)
        sources[name] = p
        if on_file is not None:
            on_file()
    if len(names) < min_images:
        raise InputError(f"only {len(names)} image{'s' * (len(names) != 1)}; structure from motion needs at least "
                         f"{min_images}", folder, "add more photos of the scene from different viewpoints")
    if len(digests) == 1:
        raise InputError(f"all {len(names)} images are identical", folder,
                         "take photos from different viewpoints (move the camera between shots)")
    if shared_camera and len(set(sizes.values())) > 1:
        first = names[0]
        odd = next(n for n in names if sizes[n] != sizes[first])
        raise InputError(f"image is {sizes[odd][0]}x{sizes[odd][1]} but {first} is {sizes[first][0]}x{sizes[first][1]}",
                         sources[odd], "use --per-image-cameras for photos from different cameras or sizes")
    return StagedImages(dest, sorted(names), sources, sizes, rotated)


def stage_masks(mask_dir: Path, staged: StagedImages, dest: Path, dilate: int = 0, objects: Path | None = None) -> Path:
    """Masks for the staged images, as COLMAP wants them: ``dest/<image name>.png``, 255 where features
    may be detected (the mask's non-zero pixels), 0 elsewhere. Masks are matched to the photos by file
    stem (``IMG_1.jpg`` <- ``IMG_1.png`` or ``IMG_1.jpg.png``) and must have the photo's size.
    ``dilate``: grow each mask by this many pixels (a square of side ``2 * dilate + 1``).
    ``objects``: also write the object masks the scene keeps there (``<image name>.png``, 0 / 255, not dilated):
    white where the mask is above 127 (8-bit masks, e.g. a JPEG's), or non-zero when no mask of the set
    goes above 127 (0 / 1 masks)."""

    mask_dir, dest = Path(mask_dir), Path(dest)
    if not mask_dir.is_dir():
        raise InputError("mask folder does not exist", mask_dir, "pass the folder that holds one mask per photo")
    by_stem: dict[str, Path] = {}
    for p in _visible_files(mask_dir):
        if p.suffix.lower() in IMAGE_EXTS:
            by_stem.setdefault(Path(p.stem).stem if p.stem.lower().endswith(IMAGE_EXTS) else p.stem, p)
    dest.mkdir(parents=True, exist_ok=True)
    read = {}
    for name in staged.names:
        stem = staged.sources[name].stem
        src = by_stem.get(stem)
        if src is None:
            raise InputError(f"no mask for {staged.sources[name].name} (looked for {stem}.png)", mask_dir,
                             "give one mask per photo, named like the photo")
        with open_photo(src, "mask") as m:
            m = to_8bit(upright(m)[0]).convert("L")
        if m.size != staged.sizes[name]:
            raise InputError(f"mask is {m.size[0]}x{m.size[1]} but its photo is "
                             f"{staged.sizes[name][0]}x{staged.sizes[name][1]}", src, "give masks at the photos' size")
        if m.getextrema()[1] == 0:  # SfM would find no feature in the photo: not a reason to take more photos
            raise InputError("the mask is all black: no pixel of its photo may be matched", src,
                             "make the masks white (non-zero) where the subject is, black only where to ignore")
        read[name] = m
        m = m.point(lambda v: 255 if v > 0 else 0)
        if dilate > 0:
            m = m.filter(ImageFilter.MaxFilter(2 * dilate + 1))
        m.save(dest / f"{name}.png")
    if objects is not None:
        objects.mkdir(parents=True, exist_ok=True)
        cut = 127 if any(m.getextrema()[1] > 127 for m in read.values()) else 0
        for name, m in read.items():
            m.point(lambda v: 255 if v > cut else 0).save(objects / f"{name}.png")
    return dest


MIN_SIDE = 16
"""Shortest side (pixels) of a photo or a video's frame given to SfM: pycolmap's feature extraction crashed the process
on 1-, 4- and 8-pixel photos instead of failing."""


def check_sizes(staged: StagedImages, video: Path | None = None) -> None:
    """Refuse a photo (or a video's frames: ``video`` is named) with a side under :data:`MIN_SIDE` pixels."""
    for name in staged.names:
        w, h = staged.sizes[name]
        if min(w, h) < MIN_SIDE:
            raise InputError(f"{'frames are' if video else 'photo is'} {w}x{h} pixels, too small to match (SfM needs "
                             f"at least {MIN_SIDE} px a side)", video or staged.sources[name],
                             "record the clip at a larger frame size (hundreds of pixels a side)" if video else
                             f"use photos at least {MIN_SIDE}x{MIN_SIDE} pixels (better hundreds)")
