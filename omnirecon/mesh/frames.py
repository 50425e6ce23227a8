"""Many frames of one mesh path: :class:`ViewCache` (renderers over different sets of a scene's views sharing one
rasterizer, each view's occlusion depths and mask falloff, one encoding per set), :func:`render_frames` (a camera path,
timed) and :func:`render_signal` (one frame of a per-view signal)."""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions, level_of_detail
from omnirecon.rays import Sources
from omnirecon.render.raster import MeshRasterizer


class ViewCache:
    """The work per source view of one mesh path over one scene's views, shared by the renderers (:class:`MeshRenderer`) of
    frames that blend different sets of them (a video whose every frame blends its nearest sources, as ``finetune
    --nearest`` scores): one rasterizer (one GL context, the mesh uploaded once), each view's occlusion depths
    (:func:`~omnirecon.mesh.kernel.block_depth_max` of its rasterized depth) and :func:`~omnirecon.mesh.kernel.mask_falloff` computed once, and each set of views
    encoded once (appearance maps only).

    A view's encoding is cached per *set*, not per view: Omni-Recon's encoder normalises with the batch statistics of
    the views it encodes together (BatchNorm without running averages, :mod:`omnirecon.models.omnirecon`), so a view's
    features depend on its companions. Every :meth:`renderer` therefore renders exactly what a :class:`MeshRenderer`
    built for its views alone renders (tested bit for bit). Use as a context manager (:meth:`close` frees the
    rasterizer).

    Args:
        model, mesh, options: as :class:`MeshRenderer`.
        scene: The :class:`~omnirecon.data.scene.Scene` whose views the renderers take as sources
            (:meth:`Sources.from_scene`); the mesh is in its frame.
        encodings: The encodings per set of views to share with other caches of the same model and scene (they do
            not depend on the mesh: :mod:`omnirecon.engine.lod` renders one scene through several levels of detail).
    """

    def __init__(self, model, mesh, scene, options: MeshRenderOptions | None = None, encodings: dict | None = None):
        self.model, self.scene = model, scene
        self.options = options or MeshRenderOptions()
        vertices, faces = level_of_detail(mesh, self.options.face_budget)
        self.rasterizer = MeshRasterizer(vertices, faces, backend=self.options.backend,
                                         cull_back_faces=self.options.cull_back_faces)
        """The one rasterizer of every renderer."""
        self._views: dict[str, dict[int, Tensor]] = {}
        self._features: dict[tuple[int, ...], object] = {} if encodings is None else encodings

    def renderer(self, views: list[int]) -> MeshRenderer:
        """A :class:`MeshRenderer` over the scene views ``views`` (in this order) that shares this cache."""
        views = [int(v) for v in views]
        return MeshRenderer(self.model, None, Sources.from_scene(self.scene, views), self.options, shared=(self, views))

    def features(self, views: list[int], encode):
        """``encode(sources)`` of ``views``, computed on the first call for this set (class docstring)."""
        key = tuple(views)
        if key not in self._features:
            self._features[key] = encode(Sources.from_scene(self.scene, views))
        return self._features[key]

    def per_view(self, kind: str, views: list[int], make) -> Tensor:
        """Per-view maps ``kind`` of ``views`` stacked on a first axis; ``make(k) # [1, ...]`` computes the map of
        the ``k``-th of ``views`` on its first request."""
        cache = self._views.setdefault(kind, {})
        for k, v in enumerate(views):
            if v not in cache:
                cache[v] = make(k)
        return torch.cat([cache[v] for v in views])

    def close(self) -> None:
        """Free the rasterizer's GL context."""
        self.rasterizer.close()

    def __enter__(self) -> ViewCache:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def render_signal(model, mesh, sources: Sources, camera: Cameras, signal: Tensor, background: float | Tensor = 0.0,
                  options: MeshRenderOptions | None = None) -> Tensor:
    """Blend a per-view ``signal # [K, H', W', C]`` (one map per source) at ``camera``'s surface points
    with the appearance branch's weights, ``background`` where no triangle. ``# [H, W, C]``

    One-shot :meth:`MeshRenderer.render_signal` (encodes the sources, builds and frees a renderer); keep
    a :class:`MeshRenderer` for many frames or signals instead.
    """
    with MeshRenderer(model, mesh, sources, options) as renderer:
        return renderer.render_signal(camera, signal, background)["signal"]


def render_frames(renderer: MeshRenderer, cameras: Cameras, warmup: bool = True) -> tuple[list[np.ndarray], list[float]]:
    """Render every camera of ``cameras`` with ``renderer`` as a stream (:meth:`MeshRenderer.frames`: a frame ahead;
    with ``warmup``, one untimed warm-up frame first): 8-bit frames ``# [H, W, 3]`` and the wall seconds of each frame
    (from the previous frame's arrival)."""
    if warmup:
        renderer.render(cameras[0].to(dtype=torch.float32), extras=False)
    images, seconds = [], []
    start = time.perf_counter()
    for rgb in renderer.frames(cameras[i].to(dtype=torch.float32) for i in range(len(cameras))):
        seconds.append(time.perf_counter() - start)
        images.append((rgb.float().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8))
        start = time.perf_counter()
    return images, seconds
