"""The confidence stage of the mesh pipeline (:func:`omnirecon.mesh.build.mesh_from_depths`, module docstring step
2): a depth source's maps -> the depth fusion takes, its per-pixel weights, the evidence of free space and the scales
(voxel, truncation, consistency margin) derived from them; :class:`NoDepth` when no pixel is left to fuse."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError
from omnirecon.mesh import clean, fusion
from omnirecon.mesh.depth import DepthMaps, background_pixels, without_background
from omnirecon.scene_kind import SceneKind, scene_kind

if TYPE_CHECKING:
    from omnirecon.mesh.build import MeshOptions


@dataclass
class Prepared:
    """What the confidence stage hands to the surface stages: the maps' cameras and their cleaned depth, its weights
    and evidence, and the scales derived from them."""

    cams: Cameras
    """The maps' cameras, float64."""
    depth: Tensor
    """z-depth fusion takes, 0 = none (background, occluded, outside the bounds and the masks dropped). ``# [N, H, W]``"""
    weight: Tensor
    """Per-pixel fusion weight. ``# [N, H, W]``"""
    agree: Tensor | None
    """Other maps that confirm each pixel (:func:`fusion.consistency`; ``None``: not computed). ``# [N, H, W]``"""
    free: Tensor | None
    """Pixels whose rays are empty space (outside the masks, or the known background). ``# [N, H, W]`` bool"""
    empty: Tensor | None
    """Pixels that show the scene's known background colour. ``# [N, H, W]`` bool"""
    unbounded: Tensor
    """``depth`` before the depth outside the bounds was dropped (the coherent surface's background layer and its
    evidence of free space take it). ``# [N, H, W]``"""
    dilated: Tensor | None
    """The scene's dilated object masks (all its views). ``# [V, H, W]`` bool"""
    err: float | None
    """The maps' median relative disagreement (:func:`fusion.depth_disagreement`)."""
    rel: float
    """The consistency margin (relative depth)."""
    voxel: float
    trunc: float
    footprint: float
    """Median pixel footprint at the maps' depth (scene units)."""
    occluded: float
    """Fraction of depth pixels the visibility check dropped."""


class NoDepth(InputError):
    """No depth map has a pixel to fuse: ``found`` says what the depth source gave (``source``: its name,
    ``covered``: the fraction of the maps' pixels with depth, ``empty``/``maps``: maps without any), ``lost`` which
    step left none (``"source"``, ``"background"`` or ``"occluded"``). The message and fix
    are ``omnirecon mesh``'s; a verb that meshes with other options (``reconstruct``) words its own from these."""

    CAUSES = {"source": "", "background": "all of it on the scene's known background colour",
              "occluded": "all of it behind surfaces other views see"}
    FIXES = {"stereo": "try --depth stereo+model with a checkpoint (--ckpt: a model's depth where stereo finds none), "
                       "or a larger --resolution",
             "stereo+model": "lower --min-acc (the model's depth where stereo finds none), or a larger --resolution",
             "model": "lower --min-acc, or pass a checkpoint trained on similar scenes (--ckpt)",
             "oracle": "check the scene's ground-truth mesh",
             "background": "check the scene's images: they show only its background colour",
             "occluded": "mesh fewer, better-spread --views, or check the scene's poses (omnirecon inspect)"}

    def __init__(self, found: dict, lost: str):
        self.found, self.lost = found, lost
        cause = self.CAUSES[lost]
        what = f"no depth map has a pixel to fuse: {self.found_text()}" + (f", {cause}" if cause else "")
        fix = self.FIXES.get(found["source"] if lost == "source" else lost, "check the depth source (--depth)")
        super().__init__(what, None, fix)

    def found_text(self) -> str:
        f = self.found
        return f"{f['source']} gave depth at {f['covered']:.1%} of the pixels (none in {f['empty']} of {f['maps']} maps)"


def depth_found(maps: DepthMaps) -> dict:
    """What a depth source gave: its name, the fraction of the maps' pixels with depth, the maps without any."""
    has = (maps.depth > 0).flatten(1)  # [N, HW]
    return {"source": str(maps.info.get("source", "the depth source")), "covered": float(has.float().mean()),
            "empty": int((~has.any(1)).sum()), "maps": len(has)}


def require_depth(depth: Tensor, given: DepthMaps, lost: str) -> None:
    """:class:`NoDepth` when ``depth`` has no pixel left after the step ``lost`` (``given``: the source's maps)."""
    if not bool((depth > 0).any()):
        raise NoDepth(depth_found(given), "source" if not bool((given.depth > 0).any()) else lost)


def prepare(maps: DepthMaps, scene, options: MeshOptions, masks: Tensor | None,
            kind: SceneKind | None = None) -> tuple[Prepared, DepthMaps]:
    """The confidence stage: depth, weights and evidence of ``maps`` for fusion (module docstring, 2), and ``maps``
    without the known background's pixels (what completion reads). :class:`NoDepth` when no pixel is left to fuse.
    ``kind``: the scene's (default: :func:`scene_kind` of ``scene`` with ``masks``)."""
    kind = kind or scene_kind(scene, masks is not None)
    given, empty = maps, None
    if masks is None and options.drop_background:  # the known background colour: no surface there, and (carve) empty space on its rays
        empty = background_pixels(maps, scene, options.shifts)
        maps = without_background(maps, scene, options.shifts)
    cams = maps.cameras.to(dtype=torch.float64)
    depth = maps.depth.float().cpu()
    require_depth(depth, given, "background")
    weight = (maps.confidence.float().cpu() if options.confidence else torch.ones_like(depth)) * (depth > 0)
    err = fusion.depth_disagreement(cams, depth) if len(cams) > 1 else None
    rel = max(0.01, 2.0 * (err or 0.0))
    needs = options.weights or options.complete or options.surface == "coherent"
    agree = fusion.consistency(cams, depth, rel=rel) if len(cams) > 1 and needs else None
    occluded = 0.0
    if options.occlusion > 0 and agree is not None and kind.occlusion:  # behind a surface others see: too far
        depth, weight, agree, occluded = drop_occluded(cams, depth, weight, agree, options, masks is None)
    if options.weights and agree is not None:
        weight = weight * fusion.geometric_weight(agree, len(cams))
    require_depth(depth, given, "occluded")
    diag = float((scene.bounds[1] - scene.bounds[0]).double().norm())
    footprint = fusion.pixel_footprint(cams, depth)
    voxel = options.voxel * diag if options.voxel is not None else fusion.auto_scale(cams, depth)[0]
    if options.voxel is None:  # at most max_voxels over the padded bounds
        extent = (scene.bounds[1] - scene.bounds[0]).double() + 0.1 * diag
        voxel = max(voxel, float(extent.prod() / options.max_voxels) ** (1 / 3))
    trunc = (options.trunc if options.trunc is not None else 4.0) * voxel
    if options.trunc is None and err is not None:  # room for the depth error the maps show
        trunc = max(trunc, 2.0 * err * float(depth[depth > 0].median()))
    if options.voxel is not None:  # a grid the memory holds (the derived voxel keeps to max_voxels)
        fusion.check_grid_memory(scene.bounds, voxel, trunc, options.voxel)
    unbounded = depth
    # surface points outside the bounds (sky, far background) give no fused surface (a depth inside the
    # padding would leave a sheet at the edge of the grid); completion puts them on the backdrop
    depth = torch.where(fusion.outside_bounds(cams, depth, scene.bounds, trunc), torch.zeros_like(depth), depth)
    dilated = None
    free = empty if options.carve else None
    if free is not None:
        weight = torch.where(free, torch.ones_like(weight), weight)
    if masks is not None:
        dilated = torch.from_numpy(clean.dilate_masks(masks.cpu().numpy().astype(bool), options.dilate * scene.width))
        at_maps = dilated[maps.views]
        depth = torch.where(at_maps, depth, torch.zeros_like(depth))
        unbounded = torch.where(at_maps, unbounded, torch.zeros_like(unbounded))
        if options.carve:
            free = ~at_maps
            weight = torch.where(at_maps, weight, torch.ones_like(weight))
    return Prepared(cams, depth, weight, agree, free, empty, unbounded, dilated, err, rel, voxel, trunc, footprint,
                    occluded), maps



def drop_occluded(cams: Cameras, depth: Tensor, weight: Tensor, agree: Tensor,
                  options: MeshOptions, free_space: bool = False) -> tuple[Tensor, Tensor, Tensor, float]:
    """``depth``, ``weight`` and ``agree`` without the pixels at least ``options.occlusion`` other maps see a
    confirmed surface in front of (:func:`fusion.occlusion_votes`; with ``options.occlusion_outvoted`` only where
    those maps outnumber the ``agree`` maps that confirm the pixel) and, with ``free_space``, those at least
    ``options.free_space`` other maps see past (:func:`fusion.free_space_votes`), and the fraction of depth
    pixels dropped: no observation there (neither surface nor free space), and completion does not take them."""
    trusted = agree >= 1
    votes = fusion.occlusion_votes(cams, depth, trusted=trusted, rel=options.occlusion_rel)
    bad = (votes >= options.occlusion) & (depth > 0)
    if options.occlusion_outvoted:  # more maps see past it than confirm it
        bad &= votes > agree
    if free_space and options.free_space > 0:  # in front of a surface other maps see past: too near
        past = fusion.free_space_votes(cams, depth, trusted=trusted, rel=options.free_space_rel)
        bad = bad | ((past >= options.free_space) & (depth > 0))
    frac = float(bad.sum() / max(1, int((depth > 0).sum())))
    zero = torch.zeros_like(depth)
    return torch.where(bad, zero, depth), torch.where(bad, zero, weight), torch.where(bad, zero, agree), frac

