"""Depth sources of the mesh pipeline: z-depth and a per-pixel confidence at a set of cameras.

Every source returns :class:`DepthMaps`; :func:`omnirecon.mesh.build.mesh_from_depths` takes it from
there. The sources:

* ``model`` (:func:`model_depths`): any model whose ``render_rays`` returns ``depth`` (IBRNet, GPNR,
  Omni-Recon, the plane-sweep floor). Each view's depth is rendered from its own nearest views
  (:class:`ViewGroups`; cost linear in the views), optionally at virtually shifted cameras
  (VolRecon's 25 mm offset, :func:`shifted_cameras`); confidence = accumulated opacity x how
  concentrated the ray's weights are (:func:`concentration`).
* ``stereo`` (:func:`stereo_maps`): classical multi-view stereo, :mod:`omnirecon.mesh.stereo`.
* ``oracle`` (:func:`oracle_depths`): the exact mesh's depth (procedural scenes), the target the
  pipeline is measured against.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError

DEPTH_SOURCES = ("model", "stereo", "oracle")
"""Names of the depth sources (``stereo+model``: stereo where it is confident, the model for the rest)."""


@dataclass
class DepthMaps:
    """What a depth source hands to the fusion."""

    cameras: Cameras
    """The ``N`` cameras the maps are seen from."""
    depth: Tensor
    """z-depth, 0 = none. ``# [N, H, W]`` float32"""
    confidence: Tensor
    """Per-pixel confidence in [0, 1], 0 where there is no depth. ``# [N, H, W]`` float32"""
    views: list[int]
    """The scene view behind each map (a shifted camera keeps its source view's index)."""
    info: dict = field(default_factory=dict)
    """Source name, seconds, model calls, ... (JSON-serialisable)."""


# ---------------------------------------------------------------------- model depth
def shifted_cameras(cameras: Cameras, shifts, center: Tensor) -> Cameras:
    """Virtual views: each camera moved along its own x axis by ``s * |centre - camera|`` for each
    shift ``s`` (VolRecon's 25 mm offset), orientation kept. Order: camera-major. ``N * len(shifts)``"""
    out = []
    dist = (cameras.centers - center.to(cameras.c2w)).norm(dim=-1)  # [N]
    for i in range(len(cameras)):
        for s in shifts:
            c2w = cameras.c2w[i:i + 1].clone()
            c2w[0, :3, 3] += c2w[0, :3, 0] * float(s) * dist[i]
            out.append(Cameras(cameras.fx[i:i + 1], cameras.fy[i:i + 1], cameras.cx[i:i + 1], cameras.cy[i:i + 1],
                               c2w, cameras.width, cameras.height))
    return Cameras.cat(out)


def depth_from_outputs(out: dict[str, Tensor], min_acc: float = 0.5) -> tuple[Tensor, Tensor]:
    """z-depth and validity from a model's ``render_view`` outputs. ``# [H, W]`` each.

    ``depth`` is required. With ``acc`` (density models: ``depth = sum_k w_k z_k``) the depth is
    divided by ``acc`` and pixels with ``acc < min_acc`` are invalid; a ``valid`` output (the
    plane-sweep floor: at least 2 views agree) is honoured; non-finite or non-positive depths are
    invalid.
    """
    if "depth" not in out:
        raise InputError("the model renders no depth", None, "mesh a model whose render_rays returns 'depth' "
                         "(IBRNet, GPNR, Omni-Recon or the floor)")
    depth = out["depth"].detach().float()
    valid = torch.isfinite(depth)
    if "acc" in out:
        acc = out["acc"].detach().float()
        valid &= acc >= min_acc
        depth = depth / acc.clamp_min(1e-6)
    if "valid" in out:
        valid &= out["valid"].bool()
    valid &= depth > 0
    return torch.where(valid, depth, torch.zeros_like(depth)).cpu(), valid.cpu()


def concentration(out: dict[str, Tensor], rel: float = 0.02) -> Tensor | None:
    """How concentrated each ray's weights are around its expected depth: ``1 / (1 + (s / (rel d))^2)``
    with ``s`` the weighted standard deviation of the sample depths and ``d`` the expected depth
    (1 for a ray whose weight sits at one depth). ``None`` for a model without ``weights``/``z``. ``# [H, W]``"""
    if "weights" not in out or "z" not in out or out["weights"].shape != out["z"].shape:
        return None
    w, z = out["weights"].detach().float(), out["z"].detach().float()  # [H, W, S]
    acc = w.sum(-1).clamp_min(1e-6)
    d = (w * z).sum(-1) / acc
    spread = ((w * (z - d[..., None]) ** 2).sum(-1) / acc).sqrt()
    return (1.0 / (1.0 + (spread / (rel * d.clamp_min(1e-6))) ** 2)).cpu()


class ViewGroups:
    """Which sources render each depth map: every view with all ``views`` as sources when there are at
    most ``k`` of them, else each view with itself and its ``k - 1`` nearest other views (by camera
    distance), so the number of model calls grows linearly with the views."""

    def __init__(self, cameras: Cameras, views: list[int], k: int):
        self.views = list(views)
        if len(self.views) <= k:
            self.sources = [list(self.views) for _ in self.views]
        else:
            from omnirecon.cameras import nearest_views

            cams = cameras[self.views].to(dtype=torch.float64)
            near = nearest_views(cams, cams, k - 1, exclude=torch.arange(len(self.views)))
            self.sources = [[v] + [self.views[j] for j in near[i].tolist()] for i, v in enumerate(self.views)]


@torch.no_grad()
def model_depths(model, scene, views, neighbours: int = 3, shifts=(0.0,), chunk: int = 4096, min_acc: float = 0.5,
                 device="cpu", on_view=None, fine_pass: bool = True, need: Tensor | None = None) -> DepthMaps:
    """Depth of ``model`` at each of ``views`` shifted by each of ``shifts`` (:func:`shifted_cameras`),
    each rendered from its :class:`ViewGroups` sources (``fine_pass``: a two-pass model's pass, see
    ``render_view``); encodings are shared between views with the same sources. ``info`` counts the
    ``encode`` and ``render_view`` calls and the rays rendered.

    ``need # [len(views), H, W]`` bool: render only those pixels of each view (all its maps); the rest get
    no depth, and a view needing none is neither encoded nor rendered (``stereo+model``: the model only
    fills the pixels stereo left empty)."""
    from omnirecon.models.base import Sources

    groups = ViewGroups(scene.cameras, list(views), max(1, neighbours))
    centre = scene.bounds.double().mean(0)
    cams, depths, confs, owners = [], [], [], []
    cache: dict[tuple, object] = {}
    renders = encodes = rays = 0
    start = time.perf_counter()
    H, W = scene.height, scene.width
    for i, (view, srcs) in enumerate(zip(groups.views, groups.sources)):
        pixels = None if need is None else need[i].reshape(-1).nonzero()[:, 0]
        key = tuple(srcs)
        if key not in cache and (pixels is None or len(pixels)):
            if len(cache) > 4:
                cache.clear()
            cache[key] = model.encode(Sources.from_scene(scene, srcs).to(device))
            encodes += 1
        for cam in shifted_cameras(scene.cameras[[view]], shifts, centre):
            if pixels is not None and not len(pixels):  # nothing to fill in this view
                cams.append(cam)
                depths.append(torch.zeros(H, W))
                confs.append(torch.zeros(H, W))
                owners.append(view)
                if on_view is not None:
                    on_view()
                continue
            out = model.render_view(cache[key], cam.to(device=device, dtype=scene.images.dtype), chunk=chunk,
                                    fine_pass=fine_pass, pixels=pixels)
            renders += 1
            rays += H * W if pixels is None else len(pixels)
            if pixels is not None:  # back to full maps: the pixels not rendered get nothing
                out = {k: scattered(v, pixels, H, W) for k, v in out.items()}
            d, v = depth_from_outputs(out, min_acc)
            conf = torch.ones_like(d)
            if "acc" in out:
                conf = conf * out["acc"].detach().float().clamp(0, 1).cpu()
            c = concentration(out)
            if c is not None:
                conf = conf * c
            cams.append(cam)
            depths.append(d)
            confs.append(torch.where(v, conf, torch.zeros_like(conf)))
            owners.append(view)
            if on_view is not None:
                on_view()
    return DepthMaps(Cameras.cat(cams), torch.stack(depths), torch.stack(confs), owners,
                     {"source": "model", "seconds": time.perf_counter() - start,
                      "model_calls": {"encode": encodes, "render_view": renders, "rays": rays},
                      "sources_per_map": len(groups.sources[0])})


def scattered(values: Tensor, pixels: Tensor, height: int, width: int) -> Tensor:
    """Per-pixel ``values # [M, ...]`` at flat ``pixels # [M]`` of an image, zero elsewhere. ``# [H, W, ...]``"""
    full = torch.zeros((height * width, *values.shape[1:]), dtype=values.dtype, device=values.device)
    full[pixels.to(values.device)] = values
    return full.reshape(height, width, *values.shape[1:])


# ---------------------------------------------------------------------- stereo and the oracle
def stereo_maps(scene, views, options=None, on_view=None) -> DepthMaps:
    """Classical stereo depth (:func:`omnirecon.mesh.stereo.stereo_depths`) at ``views``; a view that has no
    neighbour to rectify against sideways (a walk's photos) takes plane-sweep stereo against its nearest views
    instead (:func:`omnirecon.mesh.sweep.sweep_depths`)."""
    from omnirecon.mesh.stereo import stereo_depths

    start = time.perf_counter()
    views = list(views)
    out = stereo_depths(scene.images, scene.cameras, views, scene.bounds, options, on_view)
    unpaired = [k for k, pairs in enumerate(out["pairs"]) if not pairs]  # a walk's views: no sideways baseline
    swept = {}
    if unpaired and len(views) > 1:
        from omnirecon.mesh.sweep import sweep_depths

        swept = sweep_depths(scene.images, scene.cameras, [views[k] for k in unpaired], views, scene.bounds,
                             scene.near, scene.far)
        out["depth"][unpaired], out["confidence"][unpaired] = swept["depth"], swept["confidence"]
    seconds = time.perf_counter() - start
    return DepthMaps(scene.cameras[views], out["depth"], out["confidence"], views,
                     {"source": "stereo", "seconds": seconds, "seconds_per_view": seconds / max(1, len(views)),
                      "pairs": out["pairs"], "stereo_options": out["options"],
                      "unconfirmed_dropped": out["unconfirmed_dropped"],
                      "plane_sweep": {"views": [views[k] for k in unpaired], "neighbours": swept.get("neighbours", [])}})


def oracle_depths(scene, views, shifts=(0.0,)) -> DepthMaps:
    """The exact depth at ``views`` (shifted by ``shifts``): the scene's exact mesh rendered, or its
    stored depth maps at unshifted views. :class:`InputError` for a scene with neither."""
    from omnirecon.mesh.geometry import ground_truth_mesh, mesh_depth

    views = list(views)
    start = time.perf_counter()
    cams = shifted_cameras(scene.cameras[views], shifts, scene.bounds.double().mean(0))
    owners = [v for v in views for _ in shifts]
    gt = ground_truth_mesh(scene)
    if gt is not None:
        depth = torch.from_numpy(np.stack([mesh_depth(gt, cams[i]) for i in range(len(cams))])).float()
    elif scene.depths is not None and all(s == 0 for s in shifts):
        depth = scene.depths[owners].float()
    else:
        raise InputError("the oracle needs the scene's exact depth (procedural scenes)", scene.path,
                         "use --depth stereo or --depth model")
    return DepthMaps(cams, depth, (depth > 0).float(), owners,
                     {"source": "oracle", "seconds": time.perf_counter() - start})


def downscaled(scene, long_side: int):
    """``scene`` with its images (area) and masks (nearest) at most ``long_side`` px on the long side and its
    cameras rescaled to match (``scene`` itself when it is no larger): the model's depth for
    ``stereo+model`` is rendered at its eval resolution, not the photos'."""
    import dataclasses

    import torch.nn.functional as F

    scale = long_side / max(scene.width, scene.height)
    if scale >= 1:
        return scene
    cams = scene.cameras.rescaled(scale)
    size = (cams.height, cams.width)
    images = F.interpolate(scene.images.permute(0, 3, 1, 2), size=size, mode="area").permute(0, 2, 3, 1)
    masks = None if scene.masks is None else \
        F.interpolate(scene.masks[:, None].float(), size=size, mode="nearest")[:, 0] > 0.5
    return dataclasses.replace(scene, images=images.contiguous(), cameras=cams, masks=masks, depths=None,
                               normals=None, labels=None)


def holes(stereo: DepthMaps, scene, inside: Tensor | None = None) -> Tensor:
    """The pixels of ``stereo``'s (unshifted) maps the mesh pipeline would take from a fallback depth: no
    stereo depth, and not the scene's background colour (:func:`without_background`; scenes without
    masks) or, with ``inside # [N, H, W]`` bool (the dilated object masks of all the scene's views),
    inside them. ``# [len(stereo.views), H, W]`` bool"""
    need = stereo.depth <= 0
    if inside is None:
        probe = DepthMaps(stereo.cameras, torch.ones_like(stereo.depth), torch.ones_like(stereo.depth), stereo.views)
        return need & (without_background(probe, scene).depth > 0)
    return need & inside[stereo.views].to(need.device)


def needed_at(need: Tensor, height: int, width: int) -> Tensor:
    """The pixels of a ``height x width`` grid that :func:`upsampled` (nearest) reads to fill the pixels
    ``need # [N, H, W]`` of the finer grid. ``# [N, height, width]`` bool"""
    import torch.nn.functional as F

    N, H, W = need.shape
    if (H, W) == (height, width):
        return need.clone()
    index = torch.arange(height * width, dtype=torch.float64).reshape(1, 1, height, width)
    source = F.interpolate(index, size=(H, W), mode="nearest")[0, 0].long()  # [H, W]: the coarse pixel read
    out = torch.zeros(N, height * width, dtype=torch.bool)
    for i in range(N):
        out[i, source[need[i]]] = True
    return out.reshape(N, height, width)


def upsampled(maps: DepthMaps, cameras: Cameras) -> DepthMaps:
    """``maps`` read at ``cameras`` (the same views at a higher resolution): nearest depth and confidence
    (no depth blended across an edge)."""
    import torch.nn.functional as F

    if maps.depth.shape[-2:] == (cameras.height, cameras.width):
        return maps
    size = (cameras.height, cameras.width)
    depth = F.interpolate(maps.depth[:, None], size=size, mode="nearest")[:, 0]
    conf = F.interpolate(maps.confidence[:, None], size=size, mode="nearest")[:, 0]
    return DepthMaps(cameras, depth, conf, maps.views, {**maps.info, "upsampled_from": list(maps.depth.shape[-2:])})


def combine(primary: DepthMaps, fallback: DepthMaps, weight: float = 0.5) -> DepthMaps:
    """``primary``'s depth where it has some, ``fallback``'s (confidence scaled by ``weight``) elsewhere:
    stereo where it matched, the model's depth for the rest (same cameras)."""
    if primary.depth.shape != fallback.depth.shape:
        raise ValueError(f"depth maps {tuple(primary.depth.shape)} and {tuple(fallback.depth.shape)} differ")
    has = primary.depth > 0
    depth = torch.where(has, primary.depth, fallback.depth)
    conf = torch.where(has, primary.confidence, weight * fallback.confidence)
    info = {"source": f"{primary.info.get('source')}+{fallback.info.get('source')}",
            "seconds": primary.info.get("seconds", 0.0) + fallback.info.get("seconds", 0.0),
            "parts": [primary.info, fallback.info]}
    return DepthMaps(primary.cameras, depth, conf, primary.views, info)


def background_pixels(maps: DepthMaps, scene, shifts=(0.0,), tol: float = 2 / 255) -> Tensor | None:
    """The pixels of ``maps`` where the photo shows ``scene``'s known background colour (rays through empty
    space), ``None`` without a background or for shifted or resized maps. ``# [N, H, W]`` bool"""
    if scene.background is None or any(s != 0 for s in shifts) or \
            tuple(maps.depth.shape[-2:]) != (scene.height, scene.width):
        return None
    bg = torch.tensor(scene.background, dtype=scene.images.dtype)
    return (scene.images[maps.views] - bg).abs().amax(-1) <= tol  # [N, H, W]


def without_background(maps: DepthMaps, scene, shifts=(0.0,), tol: float = 2 / 255) -> DepthMaps:
    """``maps`` with no depth where the photo shows the scene's background colour (a scene composited on
    a known ``background``, e.g. procedural renders on black): there is no surface to make there, and a
    model's depth in the empty sky made sheets that hid the objects from held-out views (demo scene,
    ``bench/depth_sources.py``). Unshifted maps only (a shifted map's pixels are not the photo's)."""
    empty = background_pixels(maps, scene, shifts, tol)
    if empty is None:
        return maps
    zero = torch.zeros_like(maps.depth)
    return DepthMaps(maps.cameras, torch.where(empty, zero, maps.depth), torch.where(empty, zero, maps.confidence),
                     maps.views, {**maps.info, "background_pixels": float(empty.float().mean())})
