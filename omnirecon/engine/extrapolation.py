"""What a user sees away from the photos: the camera path a user watches, and every frame of a mesh scored there.

* :func:`user_path`: an orbit over the arc of azimuth the photos cover, reaching :data:`PATH_BEYOND` degrees past
  each end (object rigs; a capture that goes around circles fully); a walk (a forward-facing capture whose cameras
  move along their view direction) goes through its photos in order; other forward-facing captures take the LLFF
  spiral.
* :func:`score_frames`: each frame rendered by the real-time mesh path as a video renders it (each frame's nearest
  training views, the scene kind's blend and fill, :func:`omnirecon.mesh.ibr.realtime_setting`), with the defect
  shares of :mod:`omnirecon.mesh.defects` (no ground truth needed) and, where ground truth is given, PSNR (whole
  image, and over the object masks where given) and coverage.

The held-out views of an extrapolation split (:func:`omnirecon.engine.protocols.extrapolation_split`) and a
procedural scene's path frames (exact images from :func:`omnirecon.data.synth.generate.render_cameras`) are scored
the same way (``python -m bench extrapolation``); ``reconstruct`` and ``demo`` score their own path.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from omnirecon.cameras import Cameras, closest_point_to_axes
from omnirecon.engine.views import select_sources
from omnirecon.metrics import psnr
from omnirecon.scene_kind import scene_kind
from omnirecon.trajectory import is_walk

PATH_BEYOND = 15.0
"""Degrees of azimuth an object capture's path reaches past each end of the arc its photos cover."""
def user_path(scene, views: list[int], frames: int, beyond: float = PATH_BEYOND) -> tuple[Cameras, str]:
    """The camera path of module docstring through the training ``views`` of ``scene`` (their resolution and the
    intrinsics of the first): ``(cameras, kind)``, kind ``orbit``, ``walk`` or ``spiral``."""
    from omnirecon.trajectory import camera_path, default_keyframes

    cams = scene.cameras[views]
    if is_walk(cams):  # before the rig: a street walked out and back has converging axes, an "object" rig
        keys = default_keyframes(len(views))
        return camera_path(cams, "interp", frames, keyframes=keys), "walk"
    if scene_kind(scene).object:
        return camera_path(cams, "orbit", frames, closest_point_to_axes(cams), arc=None, beyond=beyond), "orbit"
    near, far = float(scene.near[views].min()), float(scene.far[views].max())
    return camera_path(cams, "spiral", frames, near=near, far=far), "spiral"


def procedural_truth(folder, scene, cams: Cameras) -> Tensor | None:
    """The exact images at ``cams`` (``scene``'s frame) of the procedural scene in ``folder``
    (:func:`omnirecon.data.synth.generate.render_cameras`), or ``None`` when ``folder`` is not one. ``# [F, H, W, 3]``"""
    from omnirecon.data.synth.generate import render_cameras
    from omnirecon.engine.protocols import is_synth

    if folder is None or not is_synth(folder):
        return None
    world = cams.transformed(scene.to_input.double())
    return torch.from_numpy(render_cameras(folder, world.c2w.numpy(), world.K[0].numpy(), cams.width, cams.height))


@dataclass
class FrameScores:
    """Per frame of :func:`score_frames` (lists of equal length) and their means."""

    defects: list[dict[str, float]]
    """:func:`omnirecon.mesh.defects.pixel_shares` of each frame."""
    psnr: list[float] = field(default_factory=list)
    """Whole-image PSNR against the truth (empty without it)."""
    psnr_masked: list[float] = field(default_factory=list)
    """PSNR over the truth's object mask (empty without masks)."""
    coverage: list[float] = field(default_factory=list)
    """Share of each frame's pixels on the mesh."""
    images: list[np.ndarray] = field(default_factory=list)
    """The rendered frames, ``# [H, W, 3]`` uint8 (with ``keep_images``)."""

    def summary(self) -> dict:
        """Means (and the worst frame by the share of defect pixels) as a JSON-ready dict."""
        out = {"frames": len(self.defects)}
        for key in ("psnr", "psnr_masked", "coverage"):
            values = getattr(self, key)
            if values:
                out[key] = float(np.mean(values))
        for kind in self.defects[0] if self.defects else ():
            out[f"defect_{kind}"] = float(np.mean([d[kind] for d in self.defects]))
        if self.defects:
            worst = int(np.argmax([d["any"] for d in self.defects]))
            out["worst_frame"] = worst
            out["worst_defect"] = self.defects[worst]["any"]
        return out


def score_frames(model, mesh, scene, train: list[int], cameras: Cameras, truth: Tensor | None = None,
                 masks: Tensor | None = None, setting: dict | None = None, fill_from: int | None = None,
                 keep_images: bool = False) -> FrameScores:
    """Render ``cameras`` through ``mesh`` (scene frame) from the ``train`` views of ``scene`` as the real-time path
    does (``setting``: :func:`~omnirecon.mesh.ibr.realtime_setting`, default the scene kind's) and score each frame:
    defect shares (completion's fills are the faces from ``fill_from`` on), and with ``truth # [F, H, W, 3]`` PSNR and
    coverage, with ``masks # [F, H, W]`` PSNR over them too."""
    from omnirecon.mesh.defects import DefectCounter
    from omnirecon.mesh.frames import ViewCache
    from omnirecon.mesh.ibr import realtime_options, realtime_setting

    setting = setting or realtime_setting(scene)
    bg = tuple(scene.background) if scene.background is not None else (1.0, 1.0, 1.0)
    opts = realtime_options(setting, background=bg, visibility=True)
    n = min(int(setting["sources"]) or len(train), len(train))
    out = FrameScores([])
    with ViewCache(model, mesh, scene, opts) as cache, \
            DefectCounter(mesh, scene.cameras[train], scene.bounds, fill_from) as counter:
        for i in range(len(cameras)):
            cam = cameras[i]
            with cache.renderer(sorted(select_sources(scene, cam, train, n))) as renderer:
                shot = renderer.render(cam.to(dtype=torch.float32))
            out.defects.append(counter(cam))
            rgb = shot["rgb"].float().clamp(0, 1).cpu()
            out.coverage.append(float(shot["mask"].float().mean()))
            if truth is not None:
                out.psnr.append(psnr(rgb, truth[i].float()))
                if masks is not None and masks[i].any():
                    out.psnr_masked.append(psnr(rgb, truth[i].float(), masks[i]))
            if keep_images:
                out.images.append((rgb.numpy() * 255 + 0.5).astype(np.uint8))
    return out
