"""Object masks carried into a processed scene (``omnirecon process --masks``).

The photos are undistorted to PINHOLE cameras (COLMAP's undistorter picks a new size and intrinsics per
camera); each mask is resampled onto the same pinhole camera here, so it stays aligned with its image: a pixel
of the undistorted camera is unprojected with that camera, projected with the photo's distorted camera
(``pycolmap.Camera``: the same models the mapper fitted) and the mask read there (bilinear, kept where at least
half of it is object). A per-image-cameras crop is applied as to the images. The scene then holds

    masks/<image stem>.png           0 / 255 at the images' size
    masks_2/, masks_4/ ...           the same downscaled like images_2/, images_4/ (area averaging, 8-bit)

which :mod:`omnirecon.data.colmap` reads as the scene's object masks (``Scene.masks``).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from PIL import Image


def undistort_mask(mask: np.ndarray, distorted, pinhole) -> np.ndarray:
    """``mask # [H, W]`` bool of a photo taken with ``distorted`` (a ``pycolmap.Camera``), resampled onto
    ``pinhole`` (its undistorted camera). ``# [h, w]`` bool at ``pinhole``'s size."""
    w, h = int(pinhole.width), int(pinhole.height)
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)  # pixel centres, COLMAP's convention
    rays = pinhole.cam_from_img(np.stack([xs.ravel(), ys.ravel()], 1))  # [h*w, 2] normalised image plane
    uv = distorted.img_from_cam(np.c_[rays, np.ones(len(rays))], check_cheirality=False)  # [h*w, 2]
    uv = (uv - 0.5).astype(np.float32).reshape(h, w, 2)  # OpenCV: pixel centres at integers
    out = cv2.remap(mask.astype(np.float32), uv[..., 0], uv[..., 1], cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return out >= 0.5


def write_masks(objects: Path, distorted_rec, undistorted_rec, scene: Path, size: tuple[int, int],
                offsets: dict[str, tuple[int, int]], factors: tuple[int, ...]) -> int:
    """Undistort the object masks ``objects/<image name>.png`` (0 / 255 at the photos' size) of every image of
    ``undistorted_rec`` into ``scene/masks`` (cropped to ``size`` ``(W, H)`` at ``offsets[name]``) and
    ``scene/masks_<f>``; returns how many were written."""
    photos = {im.name: im for im in distorted_rec.images.values()}
    w, h = size
    (scene / "masks").mkdir()
    for f in factors:
        (scene / f"masks_{f}").mkdir()
    for im in undistorted_rec.images.values():
        with Image.open(objects / f"{im.name}.png") as m:
            mask = np.asarray(m.convert("L")) > 127  # [H0, W0]
        cam = distorted_rec.cameras[photos[im.name].camera_id]
        full = undistort_mask(mask, cam, undistorted_rec.cameras[im.camera_id])
        x0, y0 = offsets.get(im.name, (0, 0))
        pic = Image.fromarray(np.where(full[y0:y0 + h, x0:x0 + w], 255, 0).astype(np.uint8))
        stem = Path(im.name).stem
        pic.save(scene / "masks" / f"{stem}.png")
        for f in factors:
            pic.resize((round(w / f), round(h / f)), Image.Resampling.BOX).save(scene / f"masks_{f}" / f"{stem}.png")
    return len(undistorted_rec.images)
