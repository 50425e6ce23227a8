"""The mesh pipeline, one path: depth source -> per-pixel confidence -> fusion -> surface -> cleaning ->
face budget -> completion.

A generalizable model has no global geometry to query on a grid (IBRNet's density and Omni-Recon's
SRDF depend on the ray), so meshes are built from depth maps:

1. **Depth** (:mod:`omnirecon.mesh.depth`): a model's rendered depth (any model, the plane-sweep
   floor included), classical stereo (:mod:`omnirecon.mesh.stereo`), stereo with the model for the
   pixels stereo leaves, or the exact depth (the oracle), each with a per-pixel confidence.
2. **Confidence**: the source's own, times the forward-backward agreement between maps.
3. **Fusion** (:mod:`omnirecon.mesh.fusion`): a weighted projective TSDF near the surfaces, voxel and
   truncation from the maps' pixel footprint and disagreement, free space carved outside masks.
4. **Surface**: marching cubes between observed voxels.
5. **Cleaning** (:mod:`omnirecon.mesh.clean`): mask votes, hidden faces, small components.
6. **Face budget**: quadric decimation.
7. **Completion** (:mod:`omnirecon.mesh.complete`): every content pixel of every view gets a surface. When the
   fills push the mesh over the budget, the fused surface is decimated to what they leave and completed again
   (:func:`fit_budget`): the written mesh holds ``max_faces``.

VolRecon's / Omni-Recon's published protocol (``shared/docs/omnirecon.md`` §6: depth at source views
shifted 25 mm along x, nearest-pixel TSDF at 1/256 of the diagonal, weight 1, cleaned with the source
masks) is the ``reference`` preset of :class:`MeshOptions`, not a second code path.

Size: the one path and its documented settings (:class:`MeshOptions`, a third of the module) belong together.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
import trimesh
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError
from omnirecon.mesh import clean, fusion
from omnirecon.mesh.complete import complete_surface
from omnirecon.mesh.depth import (
    DepthMaps,
    background_pixels,
    combine,
    downscaled,
    holes,
    model_depths,
    needed_at,
    oracle_depths,
    stereo_maps,
    upsampled,
    without_background,
)
from omnirecon.mesh.stereo import StereoOptions
from omnirecon.mesh.stereo_refine import RefineOptions, refine_depths
from omnirecon.mesh.surface import SurfaceOptions
from omnirecon.options import check_options

DTU_SHIFT = 25.0 / 684.0
"""VolRecon's virtual-view shift (25 mm along the camera x axis) over DTU's camera distance to the
scene centre (684 mm on scan24, measured), as a fraction of the camera distance."""
DTU_DILATE = 11 / 800
"""The reference dilates masks with an 11-px ellipse at 800 px image width; as a fraction of the width."""
DEPTHS = ("model", "stereo", "stereo+model", "oracle")
"""Depth sources :func:`depth_maps` knows."""
SURFACES = ("fusion", "poisson", "coherent")
"""Surfaces :func:`mesh_from_depths` makes from the depth (``MeshOptions.surface``)."""


@dataclass
class MeshOptions:
    """Every setting of the mesh pipeline (recorded with each mesh). Build presets with :meth:`preset`."""

    fusion: str = "fit"
    """The preset these settings came from: ``"fit"`` (fitted to the depth it gets) or ``"reference"``
    (VolRecon's protocol: see :data:`PRESETS`)."""
    depth: str = "model"
    """Depth source: ``model``, ``stereo``, ``stereo+model`` (stereo where it matched, the model's depth
    for the rest) or ``oracle`` (the exact depth of a procedural scene)."""
    shifts: tuple[float, ...] = (0.0,)
    """Depth maps per view: x-axis shifts as fractions of the camera's distance to the bounds centre
    (VolRecon renders at the source shifted by :data:`DTU_SHIFT`); model and oracle depth only."""
    voxel: float | None = None
    """Voxel edge as a fraction of the bounds diagonal; ``None``: half the maps' pixel footprint."""
    trunc: float | None = None
    """TSDF truncation in voxels; ``None``: 4, widened to twice the depth error the maps show."""
    neighbours: int = 3
    """Model depth: sources per depth map (each view from itself and its nearest views; cost linear in
    the views)."""
    confidence: bool = True
    """Weight each pixel by its depth source's confidence (opacity x weight concentration, stereo
    agreement)."""
    weights: bool = True
    """Weight each pixel by forward-backward reprojection agreement between the maps."""
    bilinear: bool = True
    """Read depth bilinearly at each voxel's projection (sub-pixel); ``False``: the nearest pixel."""
    carve: bool = True
    """Pixels outside the masks (with masks) or showing the scene's known background colour (without)
    mark the voxels they see through as empty."""
    band: bool = True
    """Integrate only the voxel blocks near some depth sample (the same surface, cost by surface area)."""
    max_voxels: int = 1 << 26
    """Derived voxel size: at least the size that puts this many voxels over the bounds (memory: 8 bytes
    per voxel)."""
    max_faces: int = 400_000
    """Face budget of the written mesh, completion's fills and backdrop included (0 = no limit): the fused
    surface is decimated to it, and when the fills push the total over, to what they leave (:func:`fit_budget`).
    Decimation has a floor (meshes of a few hundred faces may stay above it)."""
    depth_pass: str = "fine"
    """Which pass of a two-pass model (IBRNet, Omni-Recon) renders the depth maps: ``"fine"`` (coarse +
    importance samples, as the colour is rendered) or ``"coarse"`` (the coarse samples only, several times
    faster; on the demo scene, all views, omnirecon-tiny: a lower F-score and a larger held-out depth error)."""
    min_acc: float = 0.5
    """Models that return ``acc`` (accumulated opacity): pixels below it have no depth, and depth is
    divided by ``acc`` (the expected depth of the ray given that it hits)."""
    min_views: int = 2
    """Keep vertices inside the masks of at least this many views (when masks are given)."""
    dilate: float = DTU_DILATE
    """Mask dilation diameter as a fraction of the image width (0 = none)."""
    hull_misses: int = 1
    """With masks: drop faces outside the visual hull (:func:`clean.hull_trim`: a vertex outside the masks,
    dilated by ``hull_dilate``, of more than this many of the views that see it in frame), after cleaning
    and again after completion; -1 = off. It raised the held-out IoU and mask PSNR on dtu_scan24 and dtu_scan37:
    the IoU loss was surface outside the masks, not holes."""
    hull_keeps_seen: bool = True
    """The visual-hull trim after completion keeps every face a meshed view sees first at a pixel of its (undilated)
    mask that the trimmed mesh would leave uncovered (:func:`clean.restore_seen`): cleaning never deletes surface
    the training views see. Without it the trim left part of some training views' masks uncovered on dtu_scan24 and
    dtu_scan37; with it every training view's mask is covered, at a small cost on held-out views (the restored fill
    lies outside other views' silhouettes)."""
    hull_dilate: float = 3 / 400
    """Dilation of the masks for the visual-hull trim, a fraction of the image width (3 px at DTU's 400)."""
    cull_hidden: bool = True
    """Drop faces that no (in-mask) pixel sample of a view hits first."""
    cull_samples: float = 2.0
    """Hidden-face test: samples per voxel edge at the median depth (capped at twice this per pixel side)."""
    grow_rings: int = 1
    """Hidden-face test: restore this many rings of faces around the kept ones (slivers the samples miss)."""
    min_component: float = 0.001
    """Drop connected components with fewer faces than this fraction of the largest (the reference drops
    components under 500 faces of meshes of ~10^5-10^6 faces). A larger fraction removed much of the plane-sweep
    floor's fragmented DTU scan24 mesh and lowered its held-out IoU."""
    surface: str = "fusion"
    """``fusion``: the fused, cleaned surface as it is; ``poisson``: with object masks, screened Poisson
    over it, trimmed to the masks (:mod:`omnirecon.mesh.poisson`, needs pymeshlab), which closes the holes
    fusion leaves; without masks it is skipped (no silhouette to trim a watertight surface to); ``coherent``: one
    surface from the depth several views confirm, kept where views support it, no fills (:mod:`omnirecon.mesh.surface`,
    needs pymeshlab)."""
    coherent: SurfaceOptions = field(default_factory=SurfaceOptions)
    """Settings of the coherent surface."""
    complete: bool = True
    """Give every content pixel of every view a surface (:mod:`omnirecon.mesh.complete`)."""
    content_fill: float = 0.15
    """Without masks, on an object scene composited on a known background colour: completion also covers every
    pixel whose colour differs from the background by more than this (largest channel difference; antialiased outline
    pixels nearer the background colour stay out), and leaves out any fill that another view sees past
    (:func:`complete.occluding`, within the maps' consistency margin). Before, the surface ended ragged short of the
    content's outline (at the far edge of a procedural ground plane, seen grazing, held-out pixels beside the sky
    were uncovered), and fills in front of what other views saw hid the ground. 0: off. Held-out mesh path before
    tuning: ``python -m bench depth_sources`` (stereo+model, ``--nearest 6``), BENCHMARKS "Depth sources"."""
    drop_background: bool = True
    """Without masks: no depth where the photo shows the scene's known background colour, and (``carve``) free
    space on those rays; ``False`` keeps the sources' depth there (the "sky kept" rows of the bench)."""
    confirmed_fill: bool = True
    """Completion takes a view's own depth only where another map confirms it (:func:`fusion.consistency`),
    the rest is hole-filled from its neighbours; forward-facing captures take every depth (their borders
    have no second view). Unconfirmed fills on the demo scene were floating quads that held-out views
    saw in the sky and in front of the objects."""
    fill_occlusion: bool = True
    """Without masks: completion puts no fill in front of the surface another view sees (:func:`complete.occluding`,
    within the maps' consistency margin); on forward-facing scenes such fills go to the backdrop. Object captures
    without masks: fox's fills floated in front of the wall as shards, and the check removes them (at some
    coverage). With masks the fills keep (there the check lowered dtu_scan24's mask PSNR and coverage). Each scene
    before and after: BENCHMARKS "Depth sources"."""
    backdrop_pad: float = 0.1
    """Forward-facing scenes: completion adds the backdrop layer as a surface (:func:`complete.backdrop_sheet`:
    the bounds' far side, behind everything), over each view's image grown by this fraction of the long side
    (views between the training views see past their borders); -1 = none (the renderer's fill still shades
    those pixels, but they count as uncovered)."""
    model_side: int = 128
    """``stereo+model``: long side (px) the model's depth is rendered at before it fills stereo's holes at
    the photos' resolution (the model's eval resolution; 0 = the photos' own, ~7x the cost on fern)."""
    occlusion: int = 2
    """Visibility check before fusion: drop a pixel's depth when at least this many other maps see a confirmed
    surface in front of it on its ray (:func:`fusion.occlusion_votes`; 0 = off). Stereo's mismatches on
    dark or textureless objects land on the ground behind them ("far"), and their free space carved the
    objects: the demo's box rendered semi-transparent, the sphere's edges eroded. The check removes most of the
    too-far depth on the demo scene and raises its held-out mesh path and dtu_scan24's (ground pixels beside the
    objects' outlines are dropped too). Not on forward-facing scenes: on fern it dropped much of the depth of thin
    fronds before the background and lowered the held-out score."""
    occlusion_rel: float = 0.05
    """Relative depth margin of that check (a point less far in front is not a violation). With
    ``occlusion_outvoted``, 0.03 instead raised the demo scene and one procedural scene but lowered two others (DTU
    not tried), so 0.05 is kept until that split is understood."""
    occlusion_outvoted: bool = True
    """That check drops a pixel only when the maps that see a surface in front of it outnumber the maps that confirm
    its depth (:func:`fusion.consistency` counts), not on a fixed count alone: stereo's mismatches near a dark
    object's base agree with each other and voted correct ground depth away (the demo's "skirt"). On the demo
    scene's stereo+model maps it halves the correct pixels dropped and keeps dropping the too-far ones; the held-out
    mesh path rises on the demo scene and on procedural scenes, and dtu_scan37 stays as it was (``python -m bench
    depth_sources --rows "demo:stereo+model, nearest 6" "demo:stereo+model, nearest 6, angle blend"``). Dropping
    only when the votes exceed twice the confirmations, or trusting only points two maps confirm, scored lower."""
    free_space: int = 0
    """With that check, object captures without masks: also drop a pixel's depth when at least this many other
    maps see past its point (:func:`fusion.free_space_votes`: all 4x4 pixels around its projection hold trusted
    depth more than ``free_space_rel`` farther; 0 = off). Stereo gives the ground beside a dark object's base the
    object's depth. On the demo scene, 0 -> 2 raised the whole image, the sphere and the ground a little and lowered
    the box (3 maps, a 2x2 window or down-weighting instead of dropping did no better). Off: on one procedural
    scene the stages after fusion ran for more than ten CPU-minutes without finishing with it: not yet
    understood."""
    free_space_rel: float = 0.03
    """Relative depth margin of that check."""
    fill_holes: int = 1000
    """Object captures without masks: after the face budget, close every hole of the fused surface whose boundary
    has at most this many edges (:func:`clean.close_holes`: pymeshlab's hole closing after repairing non-manifold
    edges, else the simple loops of :func:`clean.close_small_holes`; 0 = off). Fusion leaves holes where stereo's
    mismatches on dark objects and beside outlines were dropped or carved, and completion's per-pixel fills
    leave cracks between themselves and the fused surface when seen from between the training views; closing them
    halves the held-out pixels of the demo scene that see no surface and raises its held-out mesh path (fewer
    edges gained less, more about the same). Not on forward-facing scenes (their backdrop layer covers the gaps)
    nor with object masks (DTU: not tried; the hull trim and completion there work inside the masks)."""
    fill_holes_cpu_seconds: float = 60.0
    """CPU-time limit of that hole closing (pymeshlab's, run in a child process: it once ran for more than ten
    CPU-minutes on a fused mesh); past it the simple-loop closer (:func:`clean.close_small_holes`) does the job and
    the face counts record ``holes_filled_timed_out``."""
    close_holes: int = 8
    """After the face budget, close every hole whose boundary is a simple loop of at most this many edges
    (:func:`clean.close_small_holes`; 0 = off): marching cubes' pinholes, which the mesh path showed as
    background specks on the demo's ground."""
    stereo: StereoOptions = field(default_factory=StereoOptions)
    """Settings of the stereo depth source."""
    refine: str = "stereo"
    """Photometric refinement of the stereo maps (:mod:`omnirecon.mesh.stereo_refine`), object captures without
    masks only: ``none``, ``stereo`` (the stereo maps before the model fills their holes) or ``all`` (the maps
    fusion gets). It removes stereo's bias toward the ground behind dark objects; on the demo scene ``none`` ->
    ``stereo`` raised the held-out mesh path (cone and sphere most; the box's lower edges recede), and ``all``
    scored lower than ``stereo``. It costs a few CPU-seconds. Not on forward-facing scenes nor with masks (not
    tried there)."""
    refine_options: RefineOptions = field(default_factory=RefineOptions)
    """Settings of that refinement."""
    chunk: int = 4096
    """Rays per rendering chunk."""
    voxel_chunk: int = 1 << 20
    """Voxels projected at once during fusion."""

    @classmethod
    def preset(cls, name: str, **overrides) -> MeshOptions:
        """The settings of preset ``name`` (:data:`PRESETS`) with ``overrides`` on top."""
        if name not in PRESETS:
            raise InputError(f"--fusion must be one of {', '.join(PRESETS)}, got {name!r}", None, "use --fusion fit")
        return cls(**{**PRESETS[name], **overrides, "fusion": name})

    def check(self) -> None:
        if self.fusion not in PRESETS:
            raise InputError(f"--fusion must be one of {', '.join(PRESETS)}, got {self.fusion!r}", None, "use --fusion fit")
        if self.depth not in DEPTHS:
            raise InputError(f"--depth must be one of {', '.join(DEPTHS)}, got {self.depth!r}", None, "use --depth stereo")
        if self.depth_pass not in ("coarse", "fine"):
            raise InputError(f"--depth-pass must be coarse or fine, got {self.depth_pass!r}", None, "use --depth-pass fine")
        if not self.shifts or not all(math.isfinite(s) and abs(s) < 1 for s in self.shifts):
            raise InputError(f"--shifts must be finite fractions in (-1, 1), got {list(self.shifts)}", None,
                             f"use e.g. --shifts {DTU_SHIFT:.4f}")
        if self.hull_misses < -1 or not (math.isfinite(self.hull_dilate) and 0 <= self.hull_dilate < 0.1):
            raise InputError(f"hull_misses must be >= -1 and hull_dilate in [0, 0.1), got {self.hull_misses}, "
                             f"{self.hull_dilate}", None, "use e.g. 1 and 0.0075")
        if not (math.isfinite(self.content_fill) and 0 <= self.content_fill < 1):
            raise InputError(f"content_fill must be in [0, 1), got {self.content_fill}", None, "use e.g. 0.15 (0: off)")
        if self.neighbours < 1:
            raise InputError(f"neighbours must be >= 1, got {self.neighbours}", None, "use e.g. 3")
        if self.max_voxels < 1000:
            raise InputError(f"max_voxels must be at least 1000, got {self.max_voxels}", None, "use e.g. 67108864")
        if self.model_side < 0 or 0 < self.model_side < 8:
            raise InputError(f"model_side must be 0 or at least 8 px, got {self.model_side}", None, "use e.g. 128")
        if self.surface not in SURFACES:
            raise InputError(f"--surface must be one of {', '.join(SURFACES)}, got {self.surface!r}", None,
                             "use --surface coherent")
        self.coherent.check()
        if not (math.isfinite(self.cull_samples) and self.cull_samples > 0) or self.grow_rings < 0:
            raise InputError(f"cull_samples must be > 0 and grow_rings >= 0, got {self.cull_samples}, {self.grow_rings}",
                             None, "use e.g. 2 and 1")
        if not (math.isfinite(self.fill_holes_cpu_seconds) and self.fill_holes_cpu_seconds > 0):
            raise InputError(f"fill_holes_cpu_seconds must be > 0, got {self.fill_holes_cpu_seconds}", None,
                             "use e.g. 60")
        if self.close_holes < 0 or self.fill_holes < 0:
            raise InputError(f"close_holes and fill_holes must be >= 0 (edges of the largest hole closed), got "
                             f"{self.close_holes}, {self.fill_holes}",
                             None, "use e.g. 8 (0 = off)")
        if not 0 <= self.free_space <= 8 or not (math.isfinite(self.free_space_rel) and 0 < self.free_space_rel < 1):
            raise InputError(f"free_space must be in 0-8 and free_space_rel in (0, 1), got {self.free_space}, "
                             f"{self.free_space_rel}", None, "use e.g. 2 and 0.03")
        if not 0 <= self.occlusion <= 8 or not (math.isfinite(self.occlusion_rel) and 0 < self.occlusion_rel < 1):
            raise InputError(f"occlusion must be in 0-8 and occlusion_rel in (0, 1), got {self.occlusion}, "
                             f"{self.occlusion_rel}", None, "use e.g. 2 and 0.05")
        self.stereo.check()
        self.refine_options.check()
        check_options("mesh", self, memory=False)  # voxel, trunc, min_acc, max_faces, chunk...: omnirecon/options.py
        if self.refine not in ("none", "stereo", "all"):
            raise InputError(f"refine must be none, stereo or all, got {self.refine!r}", None, "use refine='stereo'")


PRESETS: dict[str, dict] = {
    "fit": {},
    "reference": {"shifts": (DTU_SHIFT,), "voxel": 1 / 256, "trunc": 3.0, "neighbours": 1 << 30, "confidence": False,
                  "weights": False, "bilinear": False, "carve": False, "band": False, "max_faces": 0,
                  "cull_samples": 4.0, "grow_rings": 0, "complete": False, "hull_misses": -1, "occlusion": 0,
                  "close_holes": 0, "fill_holes": 0},
}
"""Settings per preset (on top of :class:`MeshOptions`' defaults, the ``fit`` preset). ``reference``:
VolRecon's protocol: every depth map from all the views, rendered at the views shifted 25 mm, nearest-
pixel depth, weight 1, voxel 1/256 of the bounds diagonal, truncation 3 voxels, 4 hidden-face samples per
voxel edge, no face budget, no completion."""


@dataclass
class MeshResult:
    """What the pipeline made."""

    mesh: trimesh.Trimesh
    """The mesh, scene frame."""
    info: dict
    """Settings, face counts after each stage, seconds per stage (JSON-serialisable)."""
    cameras: Cameras
    """The cameras the depth maps were made at."""
    depths: Tensor
    """The fused z-depth maps, 0 = none. ``# [N, H, W]``"""


# ---------------------------------------------------------------------- depth
def depth_maps(options: MeshOptions, scene, views, model=None, device="cpu", on_view=None,
               masks: Tensor | None = None) -> DepthMaps:
    """The depth maps of ``options.depth`` at ``views`` of ``scene`` (``model`` for model depth). ``stereo+model``
    renders the model only at the pixels fusion takes from it (:func:`holes`; inside the dilated ``masks``)."""
    views = list(views)
    if options.depth in ("model", "stereo+model") and model is None:
        raise InputError(f"--depth {options.depth} needs a model", None, "pass --ckpt or --model floor, or --depth stereo")

    if options.depth in ("model", "stereo+model"):
        model.to(device).eval()
    kw = {"device": device, "on_view": on_view, "fine_pass": options.depth_pass == "fine"}
    if options.depth == "model":
        return model_depths(model, scene, views, options.neighbours, options.shifts, options.chunk, options.min_acc, **kw)
    if options.depth == "oracle":
        return oracle_depths(scene, views, options.shifts)
    stereo = stereo_maps(scene, views, options.stereo, on_view)
    if masks is None and options.drop_background:  # no surface where the photo shows the known background colour
        stereo = without_background(stereo, scene)  # (fusion drops it anyway): not refined, not propagated
    refine = options.refine if scene.rig != "forward" and masks is None else "none"  # object captures without masks
    if refine == "stereo" or (refine == "all" and options.depth == "stereo"):
        stereo = refined(stereo, scene, options)
    if options.depth == "stereo":
        return stereo
    # the model's depth at most model_side px, read at the photos' pixels, only where stereo left holes
    at = downscaled(scene, options.model_side) if options.model_side else scene
    inside = None if masks is None else \
        torch.from_numpy(clean.dilate_masks(masks.cpu().numpy().astype(bool), options.dilate * scene.width))
    need = needed_at(holes(stereo, scene, inside), at.height, at.width)
    low = model_depths(model, at, views, options.neighbours, (0.0,), options.chunk, options.min_acc, need=need, **kw)
    both = combine(stereo, upsampled(low, stereo.cameras))
    return refined(both, scene, options) if refine == "all" else both


def refined(maps: DepthMaps, scene, options: MeshOptions) -> DepthMaps:
    """``maps`` (unshifted, at the photos' resolution) refined photometrically (:func:`refine_depths`)."""
    t = time.perf_counter()
    depth = refine_depths(scene.images, scene.cameras, maps.views, maps.depth, options.refine_options)
    return DepthMaps(maps.cameras, depth, maps.confidence, maps.views,
                     {**maps.info, "refined": options.refine, "refine_seconds": time.perf_counter() - t})



# ---------------------------------------------------------------------- the pipeline
class StageClock:
    """One timer for the pipeline's named stages: ``with clock("fuse"):`` announces the stage (``on_stage``) and adds
    its wall seconds to ``seconds[key]`` (the name with spaces as underscores; a stage that runs again adds up)."""

    def __init__(self, on_stage=None):
        self.seconds: dict[str, float] = {}
        self._say = on_stage or (lambda name: None)

    @contextmanager
    def __call__(self, name: str, key: str | None = None):
        self._say(name)
        key = key or name.replace(" ", "_")
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[key] = self.seconds.get(key, 0.0) + time.perf_counter() - start


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


def prepare(maps: DepthMaps, scene, options: MeshOptions, masks: Tensor | None) -> tuple[Prepared, DepthMaps]:
    """The confidence stage: depth, weights and evidence of ``maps`` for fusion (module docstring, 2), and ``maps``
    without the known background's pixels (what completion reads). :class:`NoDepth` when no pixel is left to fuse."""
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
    if options.occlusion > 0 and agree is not None and scene.rig != "forward":  # behind a surface others see: too far
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


def mesh_from_depths(maps: DepthMaps, scene, views, options: MeshOptions, masks: Tensor | None = None,
                     device="cpu", stages: dict | None = None, on_stage=None) -> MeshResult:
    """Depth maps of ``scene`` -> its mesh (scene frame), every stage after the depth source.

    Stages: ``confidence`` (:func:`prepare`), then the surface (``options.surface``): ``fusion`` / ``poisson``:
    ``fuse`` -> ``marching cubes`` -> ``clean`` -> ``decimate`` -> (``poisson``) -> ``complete``
    (:func:`fused_surface`); ``coherent``: ``coherent surface`` -> ``decimate`` (:func:`coherent_stage`).

    Args:
        maps: The depth source's maps (:func:`depth_maps`).
        views: The scene's views the mesh is for: cleaning tests visibility against them and completion
            covers them.
        masks: Object masks of ``scene`` (all its views, ``# [N, H, W]`` bool): carve free space, clean and
            complete inside them (object captures). ``None``: keep the background.
        stages: Filled with the mesh after each stage when given.
        on_stage: Called with the name of each stage as it starts (progress bars).
    """
    views = list(views)
    clock = StageClock(on_stage)
    with clock("confidence"):
        prep, maps = prepare(maps, scene, options, masks)
    if options.surface == "coherent":
        mesh, counts, completion, surface = coherent_stage(prep, maps, scene, views, options, masks, clock, stages)
    else:
        mesh, counts, completion, volume = fused_surface(prep, maps, scene, views, options, masks, device, clock,
                                                         stages)
        surface = {"grid": list(volume.shape)}
    counts["final"] = len(mesh.faces)  # what is written: after decimation, hole closing, Poisson and completion
    depth = prep.depth
    info = {"voxel": prep.voxel, "trunc": prep.trunc, "grid": surface.get("grid", []), "depth_disagreement": prep.err,
            "consistency_rel": prep.rel, "faces": counts, "seconds": clock.seconds, "views": views,
            "options": asdict(options), "depth_maps": len(maps.cameras),
            "valid_depth_fraction": float((maps.depth > 0).float().mean()), "masks": masks is not None,
            "depth_source": maps.info, "vertices": len(mesh.vertices), "completion": completion,
            "mean_weight": float(prep.weight[depth > 0].mean()) if (depth > 0).any() else 0.0,
            "occluded_dropped": prep.occluded, "surface": {k: v for k, v in surface.items() if k != "grid"}}
    return MeshResult(mesh, info, maps.cameras, maps.depth)


def fused_surface(prep: Prepared, maps: DepthMaps, scene, views, options: MeshOptions, masks: Tensor | None, device,
                  clock: StageClock, stages: dict | None):
    """TSDF fusion -> marching cubes -> cleaning -> face budget -> (screened Poisson) -> completion: ``(mesh, face
    counts, completion's record, the volume)``."""
    with clock("fuse"):
        volume = fusion.fuse(prep.cams, prep.depth, scene.bounds, prep.voxel, prep.trunc, prep.weight, prep.free,
                             options.voxel_chunk, options.bilinear, device, band=options.band)
    with clock("marching cubes"):
        mesh = fusion.extract_mesh(volume)
    counts = {"marching_cubes": len(mesh.faces)}
    if stages is not None:
        stages["marching_cubes"] = mesh
    view_cams = scene.cameras[views].to(dtype=torch.float64)
    view_masks = None if prep.dilated is None else prep.dilated[views].numpy()
    hull = None if masks is None or options.hull_misses < 0 else \
        clean.dilate_masks(masks[views].cpu().numpy().astype(bool), options.hull_dilate * scene.width)
    with clock("clean"):
        ss = int(np.clip(np.ceil(options.cull_samples * prep.footprint / prep.voxel), 1,
                         max(1, int(2 * options.cull_samples))))
        mesh, cleaned = clean.clean_mesh(mesh, view_cams, view_masks, options, ss, stages)
        counts.update(cleaned)
        if hull is not None:
            mesh = clean.hull_trim(mesh, view_cams, hull, options.hull_misses)
            counts["hull"] = len(mesh.faces)
    fill = scene.rig != "forward" and masks is None
    with clock("decimate"):
        fused = within_budget(mesh, options.max_faces, options, counts, fill=fill)
    if stages is not None:
        stages["decimated"] = fused

    def surface_and_fills(fused: trimesh.Trimesh):
        """``fused`` -> (Poisson, when asked) -> completion: the written mesh and completion's record."""
        mesh, completion = fused, None
        if options.surface == "poisson" and view_masks is not None:
            from omnirecon.mesh.poisson import poisson_surface

            with clock("poisson"):
                mesh, counts["poisson"] = poisson_surface(mesh, view_cams, view_masks)
            if stages is not None:
                stages["poisson"] = mesh
        if options.complete:
            with clock("complete"):
                mesh, completion = completed(mesh, prep, maps, scene, views, options, masks, hull, counts)
            if stages is not None:
                stages["completed"] = mesh
        return mesh, completion

    mesh, completion = surface_and_fills(fused)
    if options.max_faces and len(mesh.faces) > options.max_faces:  # the budget holds for the written mesh
        mesh, completion = fit_budget(mesh, fused, completion, surface_and_fills, options, counts, fill=fill)
    return mesh, counts, completion, volume


def completed(mesh: trimesh.Trimesh, prep: Prepared, maps: DepthMaps, scene, views, options: MeshOptions,
              masks: Tensor | None, hull: np.ndarray | None, counts: dict) -> tuple[trimesh.Trimesh, dict]:
    """Completion (:func:`complete_surface`) of ``mesh`` at ``views``, then the visual-hull trim of the fills:
    ``(mesh, completion's record)``."""
    view_cams = scene.cameras[views].to(dtype=torch.float64)
    view_masks = None if prep.dilated is None else prep.dilated[views].numpy()
    view_depths = completion_depths(maps, views, options, prep.agree if scene.rig != "forward" else None)
    content = None if masks is not None or scene.rig == "forward" or options.content_fill <= 0 else \
        content_pixels(scene, views, options.content_fill, view_depths)
    surface = len(mesh.faces)
    mesh, completion = complete_surface(mesh, view_cams, view_depths, scene.bounds, view_masks,
                                        forward=scene.rig == "forward",
                                        occlusion_rel=prep.rel if options.fill_occlusion and masks is None else None,
                                        backdrop_pad=options.backdrop_pad, content=content)
    if hull is not None:  # fills from a view's own depth obey the other views' silhouettes too
        keep = clean.hull_keep(mesh, view_cams, hull, options.hull_misses)
        if options.hull_keeps_seen:  # but never what a training view sees and nothing else covers
            keep = clean.restore_seen(mesh, keep, view_cams, masks[views].cpu().numpy().astype(bool))
        mesh, surface = clean.keep_faces(mesh, keep), int(keep[:surface].sum())
    completion["surface_faces"] = surface  # the fused (or Poisson) surface's faces come first
    counts["completed"] = len(mesh.faces)
    return mesh, completion


def coherent_stage(prep: Prepared, maps: DepthMaps, scene, views, options: MeshOptions, masks: Tensor | None,
                   clock: StageClock, stages: dict | None):
    """The coherent surface (:mod:`omnirecon.mesh.surface`) -> visual-hull trim (with masks) -> face budget, plus a
    forward-facing scene's backdrop layer: ``(mesh, face counts, the backdrop's record or None, the surface's
    record)``. No fill is made."""
    from omnirecon.mesh.surface import coherent_surface

    if prep.agree is None:
        raise InputError("the coherent surface needs at least two depth maps to confirm each other", scene.path,
                         "mesh from more views, or use --surface fusion")
    fused = None
    if options.coherent.fine == "tsdf":  # the fused TSDF surface, cleaned, as the fine surface
        with clock("fuse"):
            volume = fusion.fuse(prep.cams, prep.depth, scene.bounds, prep.voxel, prep.trunc, prep.weight, prep.free,
                                 options.voxel_chunk, options.bilinear, "cpu", band=options.band)
            fused = fusion.extract_mesh(volume)
        with clock("clean"):
            view_masks = None if prep.dilated is None else prep.dilated[views].numpy()
            ss = int(np.clip(np.ceil(options.cull_samples * prep.footprint / prep.voxel), 1,
                             max(1, int(2 * options.cull_samples))))
            fused, _ = clean.clean_mesh(fused, scene.cameras[views].to(dtype=torch.float64), view_masks, options, ss)
    with clock("coherent surface", "surface"):
        mesh, record = coherent_surface(prep.cams, prep.unbounded, prep.agree, prep.voxel, prep.rel, scene.bounds,
                                        prep.empty, options.coherent, options.min_component, fused)
    counts = {"coherent": len(mesh.faces)}
    if stages is not None:
        stages["coherent"] = mesh
    view_cams = scene.cameras[views].to(dtype=torch.float64)
    if masks is not None and options.hull_misses >= 0:
        hull = clean.dilate_masks(masks[views].cpu().numpy().astype(bool), options.hull_dilate * scene.width)
        mesh = clean.hull_trim(mesh, view_cams, hull, options.hull_misses)
        counts["hull"] = len(mesh.faces)
    with clock("decimate"):
        mesh = clean.decimate(mesh, options.max_faces)
        counts["decimated"] = len(mesh.faces)
    backdrop = None
    if scene.rig == "forward" and options.backdrop_pad >= 0:  # the background layer: the bounds' far side
        from omnirecon.mesh.complete import backdrop_sheet

        sheet = backdrop_sheet(view_cams, scene.bounds, options.backdrop_pad)
        backdrop = {"backdrop_faces": len(sheet.faces), "surface_faces": len(mesh.faces), "fill_faces": 0}
        mesh = trimesh.util.concatenate([mesh, sheet]) if len(sheet.faces) else mesh
    if stages is not None:
        stages["completed"] = mesh
    return mesh, counts, backdrop, record


def within_budget(mesh: trimesh.Trimesh, max_faces: int, options: MeshOptions, counts: dict,
                  fill: bool) -> trimesh.Trimesh:
    """``mesh`` decimated to ``max_faces`` (0 = no limit), then its small holes closed (``options.close_holes``;
    ``options.fill_holes`` when ``fill``: object captures without masks); ``counts`` gets the face counts."""
    mesh = clean.decimate(mesh, max_faces)
    counts["decimated"] = len(mesh.faces)
    if options.close_holes:
        mesh, counts["holes_closed"] = clean.close_small_holes(mesh, options.close_holes)
    if options.fill_holes and fill:
        closer: dict = {}
        mesh, counts["holes_filled"] = clean.close_holes(mesh, options.fill_holes, options.fill_holes_cpu_seconds, closer)
        if closer["closer"] != "pymeshlab" and "outcome" in closer:  # the simple-loop closer did it instead
            counts["holes_filled_timed_out" if closer["timed_out"] else "holes_filled_failed"] = 1
    return mesh


def fit_budget(mesh: trimesh.Trimesh, fused: trimesh.Trimesh, completion: dict | None, complete_fn,
               options: MeshOptions, counts: dict, fill: bool) -> tuple[trimesh.Trimesh, dict | None]:
    """The completed ``mesh`` over ``options.max_faces``: the fused surface gets what completion leaves of the
    budget and completion runs again on it (its fills match the surface that is written); a last small overshoot
    (the coarser surface needs a few more fills) comes off the fused part. Without this a budget held only the
    fused surface, and the fills and a backdrop came on top of it; decimating the completed mesh as a whole instead
    scored lower on fern's held-out views (``python -m bench depth_sources --rows "fern:stereo+fill, nearest 6"``;
    face counts and scores per budget: BENCHMARKS "Depth sources", "Real-time mesh path").
    ``complete_fn(fused) -> (mesh, completion)`` is the pipeline after the face budget."""
    budget = options.max_faces
    extra = len(mesh.faces) - len(fused.faces)  # completion's faces (and Poisson's change)
    added = len(fused.faces) - counts["decimated"]  # the hole closers' faces
    room = budget - extra - added - budget // 50  # a margin: the fills of a coarser surface differ a little
    counts["over_budget"] = len(mesh.faces)
    if room >= budget // 4:  # the fused surface keeps at least a quarter of the budget
        fused = within_budget(fused, room, options, counts, fill)
        mesh, completion = complete_fn(fused)
    if len(mesh.faces) > budget:  # still over: trim the fused part only (it comes first)
        n = completion["surface_faces"] if completion is not None else 0
        rest = len(mesh.faces) - n
        if n > 0 and budget - rest >= budget // 8:
            part = clean.decimate(trimesh.Trimesh(mesh.vertices, mesh.faces[:n], process=False), budget - rest)
            fills = trimesh.Trimesh(mesh.vertices, mesh.faces[n:], process=False)
            fills.remove_unreferenced_vertices()
            mesh = trimesh.util.concatenate([part, fills])
        else:  # the fills alone fill the budget (or the order is unknown): decimate everything
            mesh = clean.decimate(mesh, budget)
    counts["budgeted"] = len(mesh.faces)
    return mesh, completion


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


def content_pixels(scene, views, tol: float, depths: Tensor | None) -> np.ndarray | None:
    """Pixels of ``views`` whose colour differs from ``scene``'s known background colour by more than ``tol``
    (largest channel difference), or ``None`` without a background colour or when completion's depth maps are
    not at the photos' size. ``# [len(views), H, W]`` bool"""
    if scene.background is None or (depths is not None and tuple(depths.shape[-2:]) != (scene.height, scene.width)):
        return None
    bg = torch.tensor(scene.background, dtype=scene.images.dtype)
    return ((scene.images[views] - bg).abs().amax(-1) > tol).cpu().numpy()


def completion_depths(maps: DepthMaps, views, options: MeshOptions, agree: Tensor | None = None) -> Tensor | None:
    """Each of ``views``' own depth map for completion (its first unshifted map; ``None`` for shifted maps or a
    view without one), with ``options.confirmed_fill`` only where ``agree`` (:func:`fusion.consistency`
    counts, ``None``: no test) says another map confirms it. ``# [len(views), H, W]``"""
    own = {v: i for i, v in reversed(list(enumerate(maps.views)))}  # first map of each view
    if any(s != 0 for s in options.shifts) or not all(v in own for v in views):
        return None
    depth = maps.depth
    if options.confirmed_fill and agree is not None:
        depth = torch.where(agree >= 1, depth, torch.zeros_like(depth))
    return torch.stack([depth[own[v]] for v in views])


def mesh_from_model(model, scene, views, options: MeshOptions | None = None, device="cpu", use_masks: bool = False,
                    progress=None) -> MeshResult:
    """Mesh of ``scene`` (normalised scene frame) from ``options.depth``'s depth at ``views``.

    Args:
        model: A :class:`~omnirecon.models.base.GeneralizableModel` whose ``render_rays`` returns ``depth``
            (``None`` for the stereo and oracle sources).
        scene: A :class:`~omnirecon.data.scene.Scene`, normally ``Scene.normalized()``.
        views: Views to make depth at; the mesh is cleaned against them and completed at them.
        use_masks: Carve, clean and complete with the scene's masks (when it has masks).
        progress: A ``rich.progress.Progress`` to report on (optional).

    Returns:
        A :class:`MeshResult`: the mesh in the scene frame, a JSON-serialisable record of the settings,
        face counts and seconds per stage, and the depth maps that were fused.
    """
    options = options or MeshOptions()
    options.check()
    views = list(views)
    n_maps = len(views) * {"model": len(options.shifts), "oracle": 0, "stereo": 1, "stereo+model": 2}[options.depth]
    task = progress.add_task("depth", total=n_maps + 5) if progress is not None else None
    advance = (lambda: progress.advance(task)) if task is not None else None

    stages_seen = []

    def on_stage(name):
        if task is not None:
            stages_seen.append(name)  # completion runs again when the face budget is hit: the bar grows with it
            progress.update(task, description=name, total=n_maps + max(5, len(stages_seen)))
            progress.advance(task)

    t, cpu = time.perf_counter(), time.process_time()
    masks = scene.masks if use_masks and scene.masks is not None else None
    maps = depth_maps(options, scene, views, model, device, advance, masks)
    render_s, depth_cpu = time.perf_counter() - t, time.process_time() - cpu
    made = mesh_from_depths(maps, scene, views, options, masks, device, on_stage=on_stage)
    made.info["seconds"] = {"render": render_s, **made.info["seconds"]}
    made.info["cpu_seconds"] = {"depth": depth_cpu, "mesh": time.process_time() - cpu - depth_cpu}
    if "model_calls" in maps.info:
        made.info["model_calls"] = maps.info["model_calls"]
        made.info["sources_per_map"] = maps.info["sources_per_map"]
    return made


def default_surface(scene=None, masks: bool = False) -> str:
    """The surface ``omnirecon mesh --surface auto`` (and so ``reconstruct`` and ``demo``) makes per scene kind, by
    what ``python -m bench extrapolation`` (held-out views beyond the photos and the path a user watches) and ``python
    -m bench depth_sources`` (interpolated held-out views) measured (BENCHMARKS "Away from the photos"):

    * a walk (cameras that move along their view direction, :func:`omnirecon.trajectory.is_walk`: a street walked
      forward, or out and back, whatever the rig): ``coherent``. Completion's fills, each from one photo's depth, are what its later
      photos and any other viewpoint see of the street;
    * every other scene: ``fusion`` (with completion): forward-facing captures, objects with masks or a known
      background colour, and objects without either.
    """
    from omnirecon.trajectory import is_walk

    cams = getattr(scene, "cameras", None)
    if cams is not None and is_walk(cams):
        return "coherent"
    return "fusion"


def default_depth(scene=None, has_model: bool = True, masks: bool = False) -> str:
    """The depth source ``omnirecon mesh --depth auto`` (and so ``reconstruct`` and ``demo``) picks per scene kind,
    by what ``python -m bench depth_sources`` measured (BENCHMARKS "Depth sources", all training views but the
    held-out ones, scored with finetune's visibility test; held-out PSNR before -> after 60 CPU-s of tuning).
    ``stereo`` below is stereo with completion (``MeshOptions.complete``, on by default; the bench's
    ``stereo+fill`` row):

    * forward-facing captures (``scene.rig == "forward"``): ``stereo``, model or not. On fern it scores a little
      above ``stereo+model`` (``--rows fern:stereo+fill fern:stereo+model``), both cover every pixel, and it needs
      no model pass;
    * object captures meshed with their masks (``--masks``): ``stereo``. On dtu_scan24 / dtu_scan37 (``--rows
      dtu_scan24:stereo+fill dtu_scan24:stereo+model ...``) it scores above ``stereo+model`` over the mask at about
      the same IoU;
    * other scenes with a model (object rigs without masks, unknown rigs): ``stereo+model`` (stereo where it
      matched, the model's coarse depth at 128 px for the rest). It scores above ``stereo`` on the demo's
      procedural scene (``--rows demo:stereo+fill demo:stereo+model``), and on a 3-view procedural capture stereo
      alone left most held-out depth uncovered (``tests/mesh/test_mesh.py::test_mesh_cli_floor``): stereo pairs
      only views within 60 degrees;
    * without a model, ``stereo``.
    """
    rig = getattr(scene, "rig", "unknown")
    if not has_model or rig == "forward" or (masks and getattr(scene, "masks", None) is not None):
        return "stereo"
    return "stereo+model"
