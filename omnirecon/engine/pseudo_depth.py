"""Stereo pseudo ground truth for training: real scenes come without depth maps, so ``--stereo-depth``
gives their training views the confident part of classical stereo depth (``mesh/stereo.py``) and the
depth loss supervises those pixels as it does procedural scenes' exact depth.

Only the scene's training views are matched (never a held-out view), at the resolution the scene is
trained at, once per scene (kept in memory: the scene bank reloads scenes it evicted).
"""

from __future__ import annotations

import dataclasses

import torch

from omnirecon.data.scene import Scene


class StereoPseudoDepth:
    """``(ref, scene) -> scene`` with ``depths`` set: stereo z-depth where at least ``need`` pairs agree
    (confidence 1), 0 (unknown) elsewhere and on every view that is not a training view."""

    def __init__(self, options=None):
        self.options = options
        self._maps: dict = {}
        self.coverage: dict[str, float] = {}
        """Fraction of training-view pixels that received a depth, per scene name (for the run's notes)."""

    def __call__(self, ref, scene: Scene) -> Scene:
        key = (ref.path, scene.height, scene.width)
        if key not in self._maps:
            from omnirecon.mesh.stereo import stereo_depths

            views = list(scene.splits.get("train") or range(len(scene)))
            out = stereo_depths(scene.images, scene.cameras, views, scene.bounds, self.options)
            depths = torch.zeros(scene.images.shape[:3], dtype=torch.float32)  # [N, H, W]
            depths[views] = torch.where(out["confidence"] >= 1.0, out["depth"], torch.zeros(()))
            self._maps[key] = depths
            self.coverage[ref.name] = float((depths[views] > 0).float().mean())
        return dataclasses.replace(scene, depths=self._maps[key])
