"""The mesh path's pixels of whole views, for scoring and tuning with gradients (``omnirecon finetune``).

Every view is rasterized once (:func:`rasterize_views`, :func:`rasterize_groups`): one surface point per covered
pixel and, per the fill, a point for every pixel the mesh misses (:func:`omnirecon.mesh.fill.shaded_surface`, as
:class:`omnirecon.mesh.ibr.MeshRenderer` does), with the occlusion test of :mod:`omnirecon.mesh.kernel` against each
source (:class:`ViewPixels`). Their colour (:func:`render_pixels`) is the same blend as the real-time renderer's:
the appearance branch (``OmniRecon.shade``, differentiable) or the angle blend's weights
(:func:`angle_blend`: :func:`omnirecon.mesh.kernel.angle_blend_weights`) over the sources' colours
(:func:`omnirecon.mesh.kernel.blend_colours`). :func:`score_held_out` scores whole held-out views with them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from omnirecon import metrics
from omnirecon.mesh.fill import CRACK_RADIUS, layer_box, shaded_surface
from omnirecon.mesh.ibr import masks_hold_scene
from omnirecon.mesh.kernel import (
    angle_blend_weights,
    blend_colours,
    block_depth_max,
    mask_factor,
    mask_falloff,
    unoccluded,
)
from omnirecon.rays import Sources
from omnirecon.render.edges import soften_edges
from omnirecon.render.raster import MeshRasterizer


@dataclass
class ViewPixels:
    """The shaded pixels of one view: first the ``covered`` ones on the mesh, then the fill's."""

    index: int
    """Scene view index."""
    origin: torch.Tensor
    """Camera centre. ``# [3]``"""
    points: torch.Tensor
    """Surface (or background-layer) point per pixel. ``# [P, 3]``"""
    pixels: torch.Tensor
    """Flat pixel indices. ``# [P]``"""
    target: torch.Tensor
    """Ground-truth colour of those pixels. ``# [P, 3]``"""
    covered: int
    """The first ``covered`` pixels lie on the mesh."""
    visible: torch.Tensor | None = None
    """Which sources see each point (the occlusion test; fill points: all), ``None`` = no test. ``# [P, K]`` bool"""
    weights: torch.Tensor | None = None
    """With ``--blend angle``: each point's fixed blend weights (:func:`angle_blend`); ``None``: the network's.
    ``# [P, K]``"""
    occlusion: torch.Tensor | None = None
    """With ``--blend angle``: the occlusion test's ``visible`` before :func:`angle_blend` narrowed it. ``# [P, K]``"""
    consensus: float = 0.0
    """With ``--blend angle``: ``--consensus`` (:func:`omnirecon.mesh.kernel.consensus_weights`; 0: off)."""
    face: torch.Tensor | None = None
    """With ``faces`` (``--tune surface``): the mesh face under each pixel, -1 off the mesh (the fill's rows).
    ``# [P]`` int64"""
    bary: torch.Tensor | None = None
    """With ``faces``: each point's barycentrics on its face (0 off the mesh). ``# [P, 3]``"""


def nearest_depth_points(surf, covered: int, cam) -> tuple[torch.Tensor, torch.Tensor]:
    """``--fill nearest`` (:func:`omnirecon.mesh.fill.nearest_fill`, the mesh renderer's ``fill="nearest"``): the points
    ``# [P, 3]`` of ``surf`` with the missed pixels within :data:`~omnirecon.mesh.fill.NEAREST_FILL_REACH` of a covered
    pixel moved to the nearest covered pixel's z-depth, and which rows moved ``# [P]`` bool."""
    from omnirecon.mesh.fill import nearest_fill

    filled, moved = nearest_fill(surf, covered, cam)
    return filled.points, moved


def rasterize_views(mesh, scene, indices, fill: bool = True, sources: list[int] | None = None,
                    tol: float = 0.01, nearest_fill: bool = False, cracks: int = CRACK_RADIUS,
                    faces: bool = False) -> list[ViewPixels]:
    """Rasterize ``mesh`` (scene frame) at each of ``indices`` once; with ``fill``, every pixel the mesh
    misses gets the mesh renderer's background layer (with ``nearest_fill``: a point at the nearest covered pixel's
    depth, :func:`nearest_depth_points`), and with ``cracks`` > 0 the missed pixels the mesh encloses a point at the
    nearest covered pixel's depth whatever ``fill`` (:func:`omnirecon.mesh.fill.shaded_surface`); with ``sources``
    (scene views), each mesh point gets the occlusion test against those views (:func:`omnirecon.mesh.kernel.unoccluded`,
    relative tolerance ``tol``); with ``faces``, each mesh point its face and barycentrics (``--tune surface``)."""
    return rasterize_groups(mesh, scene, [indices], fill, sources, tol, nearest_fill, cracks, faces)[0]


def rasterize_groups(mesh, scene, groups: list[list[int]], fill: bool = True, sources: list[int] | None = None,
                     tol: float = 0.01, nearest_fill: bool = False, cracks: int = CRACK_RADIUS,
                     faces: bool = False) -> list[list[ViewPixels]]:
    """:func:`rasterize_views` for several groups of views (tuning, held-out, validation) with one rasterizer and
    the sources' depth maps rasterized once for all of them."""
    far, bounds = float(scene.far.max()), scene.bounds.float()
    with MeshRasterizer.from_trimesh(mesh, cull_back_faces=False) as rast:
        dmax = None
        if sources:
            dmax = block_depth_max(torch.stack([rast.rasterize(scene.cameras[k], normals="none").depth
                                                for k in sources]).float())
        groups = [[view_pixels(rast, scene, i, far, bounds, fill, sources, dmax, tol, nearest_fill, cracks)
                   for i in indices] for indices in groups]
        if faces:
            for v in (v for views in groups for v in views):
                locate_faces(rast, scene, v)
        return groups


def locate_faces(rast, scene, view: ViewPixels) -> None:
    """Set ``view.face`` and ``view.bary`` (in place): the face under each of its mesh pixels (``rast.face_ids``)
    and the point's barycentrics on it (:func:`omnirecon.mesh.offsets.face_barycentrics`)."""
    from omnirecon.mesh.offsets import face_barycentrics

    n_faces = len(rast.faces)
    ids = torch.from_numpy(rast.face_ids(scene.cameras[view.index]).reshape(-1))[view.pixels[:view.covered]]
    ok = ids >= 0  # [covered] (a pixel the surface pass covers and the face pass misses: left undisplaced)
    face = torch.full((len(view.points),), -1, dtype=torch.int64)
    face[:view.covered] = torch.where(ok, ids % n_faces, -1)  # the reference backend's flipped copy: same face
    bary = torch.zeros(len(view.points), 3)
    on = face >= 0
    bary[on] = face_barycentrics(torch.from_numpy(rast.vertices), torch.from_numpy(rast.faces), face[on],
                                 view.points[on])
    view.face, view.bary = face, bary


def view_pixels(rast, scene, i: int, far: float, bounds, fill: bool, sources, dmax, tol: float,
                nearest_fill: bool, cracks: int = CRACK_RADIUS) -> ViewPixels:
    """One view of :func:`rasterize_groups`: its surface (and fill) points and, given ``dmax`` (the sources'
    block depth maxima), which sources see each point."""
    cam = scene.cameras[i]
    mode = ("nearest" if nearest_fill else "far") if fill else "background"
    surf, covered, layer = shaded_surface(rast.surface(cam), cam.to(dtype=torch.float32), far,
                                          layer_box(scene.rig, bounds), mode, cracks)
    img = scene.images[i].reshape(-1, 3)
    points = surf.points
    visible = None
    if dmax is not None:
        proj = scene.cameras[sources].to(dtype=torch.float32).project(points)
        visible = unoccluded(dmax, proj.uv.permute(0, 2, 1), proj.depth, tol).T  # [P, K]
        visible[layer] = True  # the far layer: every source
    return ViewPixels(i, cam.centers[0].float(), points, surf.pixels, img[surf.pixels].float(), covered, visible)


class ResidualColour(torch.nn.Module):
    """``--tune residual``: a colour offset over the scene's box, a coarse 3-D grid sampled trilinearly at each
    shaded point (zero outside the box, e.g. on the far layer) and added to the blend; zero at start."""

    def __init__(self, box: torch.Tensor, res: int):
        super().__init__()
        self.grid = torch.nn.Parameter(torch.zeros(1, 3, res, res, res), requires_grad=False)
        """RGB offsets, z-major. ``# [1, 3, R, R, R]``"""
        self.register_buffer("box", box.float())  # [2, 3]

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        lo, hi = self.box
        g = ((points.float() - lo) / (hi - lo).clamp_min(1e-9) * 2 - 1).reshape(1, 1, 1, -1, 3)
        v = torch.nn.functional.grid_sample(self.grid, g, align_corners=False, padding_mode="zeros")  # [1, 3, 1, 1, n]
        return v.reshape(3, -1).T  # [n, 3]


class Exposure(torch.nn.Module):
    """An affine colour per source view: ``gain_k * rgb + offset_k`` (per channel), identity at start."""

    def __init__(self, k: int):
        super().__init__()
        self.gain = torch.nn.Parameter(torch.ones(k, 1, 1, 3), requires_grad=False)
        """Per-view, per-channel gain. ``# [K, 1, 1, 3]``"""
        self.offset = torch.nn.Parameter(torch.zeros(k, 1, 1, 3), requires_grad=False)
        """Per-view, per-channel offset (0: a robust fit of the offset as well measured worse). ``# [K, 1, 1, 3]``"""

    def forward(self, sources: Sources) -> Sources:
        images = sources.images * self.gain + self.offset  # [K, H, W, 3]
        return Sources(images, sources.cameras, sources.near, sources.far, sources.rig, sources.bounds)


@torch.no_grad()
def estimate_gains(model, sources: Sources, views: list[ViewPixels], g: torch.Generator, n: int = 32768) -> torch.Tensor:
    """Per-source, per-channel exposure gain: the median over mesh pixels of the tuning views of
    ``photo / source colour`` where the source sees the point (the median ignores occluded views and
    misregistered pixels, which bias a least-squares fit toward 0). ``# [K, 1, 1, 3]``"""
    feats = encode_maps(model, sources)
    K = len(sources.cameras)
    ratios = [[] for _ in range(K)]
    per_view = max(n // len(views), 1)
    for v in views:
        idx = torch.randperm(v.covered, generator=g)[:per_view]
        seen = model.gather(feats, v.points[idx][:, None], v.origin.expand(len(idx), 3))
        rgb, mask, t = seen.rgb[:, 0], seen.mask[:, 0], v.target[idx]  # [P, K, 3], [P, K], [P, 3]
        for k in range(K):
            ok = mask[:, k] & (rgb[:, k] > 0.04).all(-1) & (t > 0.04).all(-1)
            ratios[k].append(t[ok] / rgb[ok, k])
    gains = [torch.cat(r).median(0).values if sum(len(x) for x in r) >= 16 else torch.ones(3) for r in ratios]
    return torch.stack(gains).reshape(K, 1, 1, 3)


ENCODER_GRAPH_MB = 2048
"""A tuned encoder's pass whose graph would hold more than this is checkpointed (``FPNEncoder.appearance``:
identical features and gradients, each step's encoder pass about 1.4x the CPU). The graph takes about
:data:`GRAPH_BYTES_PER_PIXEL` per source pixel (e.g. 52 sources at 401x401 hold about 3 GB); checkpointing
lowers ``finetune``'s peak resident memory and leaves the step count and the scores as they were."""


GRAPH_BYTES_PER_PIXEL = 360
"""omnirecon-tiny's encoder graph per source pixel (measured: 52 x 401 x 401 sources, 3.0 GB)."""


def encode_maps(model, sources, colours: Sources | None = None):
    """The mesh path's features: the 2-D encoder's appearance feature only (``OmniRecon.encode_appearance``: no
    pyramid maps, no feature volume). Differentiable; a pass with gradients whose graph would exceed
    :data:`ENCODER_GRAPH_MB` is checkpointed. ``colours``: the sources whose images the blend mixes (default
    ``sources``; e.g. exposure-corrected)."""
    big = sources.images[..., 0].numel() * GRAPH_BYTES_PER_PIXEL > ENCODER_GRAPH_MB * 2 ** 20
    feats = model.encode_appearance(sources, checkpoint=big and torch.is_grad_enabled())
    return feats if colours is None else replace(feats, sources=colours)


def shaded_points(view: ViewPixels, idx: torch.Tensor | None = None, surface=None) -> torch.Tensor:
    """``view``'s points (or those at ``idx``), moved by ``surface``'s offsets (``--tune surface``:
    :class:`omnirecon.mesh.offsets.SurfaceOffsets`; ``None``: as rasterized). ``# [n, 3]``"""
    points = view.points if idx is None else view.points[idx]
    if surface is None:
        return points
    return points + surface.shift(view.face if idx is None else view.face[idx],
                                  view.bary if idx is None else view.bary[idx], points, view.origin.expand_as(points))


def render_pixels(model, features, view: ViewPixels, idx: torch.Tensor | None = None, chunk: int = 16384,
                  residual: ResidualColour | None = None, surface=None) -> torch.Tensor:
    """Colours of ``view``'s pixels (or of those at ``idx``) through the appearance branch (plus ``residual``, ``--tune
    residual``), at the points moved by ``surface`` (``--tune surface``, :func:`shaded_points`). ``# [P, 3]``"""
    points = shaded_points(view, idx, surface)
    if residual is not None:
        return render_pixels(model, features, view, idx, chunk, surface=surface) + residual(points)
    weights = None if view.weights is None else (view.weights if idx is None else view.weights[idx])
    out = [point_colours(model, features, points[s:s + chunk], view.origin.expand(len(points[s:s + chunk]), 3),
                         visible_at(view, idx, s, s + chunk), None if weights is None else weights[s:s + chunk],
                         view.consensus) for s in range(0, len(points), chunk)]
    return torch.cat(out) if out else view.target.new_zeros(0, 3)


def point_colours(model, features, points: torch.Tensor, origins: torch.Tensor, visible: torch.Tensor | None,
                  weights: torch.Tensor | None = None, consensus: float = 0.0) -> torch.Tensor:
    """The mesh path's colour at ``points # [n, 3]`` seen from ``origins # [n, 3]`` (differentiable; what scores and
    tuning steps shade): with ``weights # [n, K]`` (the angle blend's, :func:`angle_blend`), those weights over the
    sources' colours (:func:`omnirecon.mesh.kernel.blend_colours`, with ``consensus``); else the appearance branch's
    over the sources ``visible # [n, K]`` bool (``None``: all; ``OmniRecon.shade``). ``# [n, 3]``"""
    if weights is not None:
        rgb = model.gather(features, points[:, None], origins).rgb[:, 0]  # [n, K, 3]
        return blend_colours(rgb, weights, consensus)
    return model.shade(features, points, origins, visible)["rgb"]


def visible_at(view: ViewPixels, idx: torch.Tensor | None = None, start: int = 0, stop: int | None = None):
    """``view.visible`` at ``idx`` (all pixels when ``None``), rows ``start:stop`` of that; ``None`` without the
    test. ``# [n, K]`` bool"""
    if view.visible is None:
        return None
    vis = view.visible if idx is None else view.visible[idx]
    return vis[start:stop]


def full_image(scene, view: ViewPixels, rgb: torch.Tensor, background=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """The whole image: ``rgb`` at the shaded pixels, ``background`` (RGB) elsewhere. ``# [H, W, 3]``"""
    img = torch.tensor(background, dtype=torch.float32).expand(scene.height * scene.width, 3).clone()
    img[view.pixels] = rgb.detach().float().clamp(0, 1)
    return img.reshape(scene.height, scene.width, 3)


def mesh_depth(scene, view: ViewPixels) -> torch.Tensor:
    """The mesh's z-depth at each pixel of ``view``, 0 where it covers none (the fill's pixels). ``# [H, W]``"""
    depth = torch.zeros(scene.height * scene.width)
    cam = scene.cameras[view.index].to(dtype=torch.float32)
    depth[view.pixels[:view.covered]] = cam.project(view.points[:view.covered]).depth[0]
    return depth.reshape(scene.height, scene.width)


def coverage_mask(scene, view: ViewPixels) -> torch.Tensor:
    """Pixels on real surface. ``# [H, W]`` bool"""
    m = torch.zeros(scene.height * scene.width, dtype=torch.bool)
    m[view.pixels[:view.covered]] = True
    return m.reshape(scene.height, scene.width)


def angle_blend(pixels: list[ViewPixels], scene, sources: list[int], k: int, source_masks: bool = True) -> None:
    """Give every point of each view in ``pixels`` its ``--blend angle`` weights (in place): the ``k`` sources
    (``k`` = 0: all) nearest by viewing angle among those in front of it, inside their image and (with the
    occlusion test) not occluded, never the view's own photo; with ``source_masks`` on a real object capture with
    masks (:func:`omnirecon.mesh.ibr.masks_hold_scene`), times
    :func:`omnirecon.mesh.kernel.mask_falloff` at each source's pixel for the points on the mesh (as the mesh renderer's
    ``MeshRenderOptions.source_masks``); ``visible`` becomes the sources with weight."""
    cams = scene.cameras[sources].to(dtype=torch.float32)
    falloff = mask_falloff(scene.masks[sources]) if source_masks and masks_hold_scene(scene) else None
    for v in pixels:
        proj = cams.project(v.points)
        seen = (proj.in_image & (proj.depth > 0)).T  # [P, K]
        if v.occlusion is None and v.visible is not None:
            v.occlusion = v.visible  # the occlusion test's result, kept: a second call starts from it again
        if v.occlusion is not None:
            seen &= v.occlusion
        if v.index in sources:  # a view never blends its own photo (validation views are sources under --nearest)
            seen[:, sources.index(v.index)] = False
        fac = None
        if falloff is not None:
            fac = mask_factor(falloff, proj.uv.permute(0, 2, 1)).T  # [P, K]
            fac[v.covered:] = 1.0  # the fill's points: off the objects where the view sees no surface
        v.weights = angle_blend_weights(v.points, v.origin, cams.centers, seen, k or len(sources), fac)
        v.visible = v.weights > 0


@torch.no_grad()
def score_held_out(model, feats, scene, held_px: list[ViewPixels], background, residual=None,
                   soften: float = 0.0, surface=None) -> dict:
    """PSNR of the held-out views: whole image, over the masks (scenes with masks) and over the pixels the mesh
    covers; ``coverage``; the ``renders`` (with ``soften``, blurred by that many pixels at the mesh's depth edges:
    ``--soften``; with ``surface``, at the points its offsets move). ``feats``: the sources' features, or a function
    of a view giving the ``(features, view)`` it renders with (each view its own sources)."""
    def render(v: ViewPixels) -> torch.Tensor:
        return render_pixels(model, *(feats(v) if callable(feats) else (feats, v)), residual=residual, surface=surface)

    renders = [soften_edges(full_image(scene, v, render(v), background), mesh_depth(scene, v), soften)
               for v in held_px]
    gts = [scene.images[v.index].float() for v in held_px]
    cover = [coverage_mask(scene, v) for v in held_px]
    r = {"psnr": float(np.mean([metrics.psnr(x, y) for x, y in zip(renders, gts)])),
         "per_view": [metrics.psnr(x, y) for x, y in zip(renders, gts)], "renders": renders,
         "coverage": float(torch.stack(cover).float().mean())}
    if scene.masks is not None:  # the objects only (a mesh cleaned with the masks has no background)
        masks = [scene.masks[v.index].bool() for v in held_px]
        r["psnr_masked"] = float(np.mean([metrics.psnr(x, y, m) for x, y, m in zip(renders, gts, masks)]))
        r["coverage_masked"] = float(sum(int((c & m).sum()) for c, m in zip(cover, masks)) /
                                     max(sum(int(m.sum()) for m in masks), 1))
        cover = [c & m for c, m in zip(cover, masks)]
    covered = [metrics.psnr(x, y, c) for x, y, c in zip(renders, gts, cover) if c.any()]
    if covered:  # appearance alone: the pixels the mesh covers (inside the masks when there are masks)
        r["psnr_covered"] = float(np.mean(covered))
    return r


