"""The mesh pipeline, one path: depth source -> per-pixel confidence -> fusion -> surface -> cleaning ->
face budget -> completion.

A generalizable model has no global geometry to query on a grid (IBRNet's density and Omni-Recon's
SRDF depend on the ray), so meshes are built from depth maps:

1. **Depth** (:mod:`omnirecon.mesh.depth`): a model's rendered depth (any model, the plane-sweep
   floor included), classical stereo (:mod:`omnirecon.mesh.stereo`), stereo with the model for the
   pixels stereo leaves, or the exact depth (the oracle), each with a per-pixel confidence.
2. **Confidence** (:mod:`omnirecon.mesh.confidence`): the source's own, times the forward-backward agreement between
   maps.
3. **Fusion** (:mod:`omnirecon.mesh.fusion`): a weighted projective TSDF near the surfaces, voxel and
   truncation from the maps' pixel footprint and disagreement, free space carved outside masks.
4. **Surface**: marching cubes between observed voxels.
5. **Cleaning** (:mod:`omnirecon.mesh.clean`): mask votes, hidden faces, small components.
6. **Face budget**: quadric decimation.
7. **Completion** (:mod:`omnirecon.mesh.complete`): every content pixel of every view gets a surface. When the
   fills push the mesh over the budget, the fused surface is decimated to what they leave and completed again
   (:func:`~omnirecon.mesh.stages.refit`): the written mesh holds ``max_faces``.

VolRecon's / Omni-Recon's published protocol (``shared/docs/omnirecon.md`` §6: depth at source views
shifted 25 mm along x, nearest-pixel TSDF at 1/256 of the diagonal, weight 1, cleaned with the source
masks) is the ``reference`` preset of :class:`MeshOptions`, not a second code path.

Steps 2-7 are named stages over one shared state, run in order under one timer (:mod:`omnirecon.mesh.stages`).

Size: the one path's entry points and its documented settings (:class:`MeshOptions`, half the module) belong
together.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace

import torch
import trimesh
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError
from omnirecon.mesh import clean
from omnirecon.mesh.depth import (
    DepthMaps,
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
from omnirecon.mesh.stages import COHERENT, FUSED, MeshState, StageClock, run
from omnirecon.mesh.stereo import StereoOptions
from omnirecon.mesh.stereo_refine import RefineOptions, refine_depths
from omnirecon.mesh.surface import SurfaceOptions
from omnirecon.options import check_options
from omnirecon.scene_kind import scene_kind

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
    depth: str = "auto"
    """Depth source: ``model``, ``stereo``, ``stereo+model`` (stereo where it matched, the model's depth
    for the rest), ``oracle`` (the exact depth of a procedural scene) or ``auto``: the scene kind's
    (:meth:`omnirecon.scene_kind.SceneKind.depth`; ``stereo+model`` with the model's coarse pass), as ``omnirecon
    mesh --depth auto`` (:func:`resolved`)."""
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
    surface is decimated to it, and when the fills push the total over, to what they leave (:func:`~omnirecon.mesh.stages.refit`).
    Decimation has a floor (meshes of a few hundred faces may stay above it)."""
    depth_pass: str = "auto"
    """Which pass of a two-pass model (IBRNet, Omni-Recon) renders the depth maps: ``"fine"`` (coarse +
    importance samples, as the colour is rendered) or ``"coarse"`` (the coarse samples only, several times
    faster; on the demo scene, all views, omnirecon-tiny: a lower F-score and a larger held-out depth error);
    ``"auto"``: coarse for ``stereo+model`` (the model only fills stereo's holes), else fine (:func:`resolved`), as
    ``omnirecon mesh --depth-pass auto``."""
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
    surface: str = "auto"
    """``fusion``: the fused, cleaned surface as it is; ``poisson``: with object masks, screened Poisson
    over it, trimmed to the masks (:mod:`omnirecon.mesh.poisson`, needs pymeshlab), which closes the holes
    fusion leaves (without masks it is skipped, and ``omnirecon mesh`` refuses it); ``coherent``: one surface from the depth several
    views confirm, kept where views support it, no fills (:mod:`omnirecon.mesh.surface`, needs pymeshlab); ``auto``:
    the scene kind's (:func:`default_surface`), as ``omnirecon mesh --surface auto``."""
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
        if self.depth not in ("auto", *DEPTHS):
            raise InputError(f"--depth must be auto or one of {', '.join(DEPTHS)}, got {self.depth!r}", None,
                             "use --depth stereo")
        if self.depth_pass not in ("auto", "coarse", "fine"):
            raise InputError(f"--depth-pass must be auto, coarse or fine, got {self.depth_pass!r}", None,
                             "use --depth-pass fine")
        if not self.shifts:  # their range: check_options below
            raise InputError("--shifts needs at least one shift", None, f"use e.g. --shifts {DTU_SHIFT:.4f}")
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
        if self.surface not in ("auto", *SURFACES):
            raise InputError(f"--surface must be auto or one of {', '.join(SURFACES)}, got {self.surface!r}", None,
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
    options = resolved(options, scene, model is not None, masks is not None)
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
    refine = options.refine if scene_kind(scene, masks is not None).object_without_masks else "none"
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
def mesh_from_depths(maps: DepthMaps, scene, views, options: MeshOptions, masks: Tensor | None = None,
                     device="cpu", stages: dict | None = None, on_stage=None) -> MeshResult:
    """Depth maps of ``scene`` -> its mesh (scene frame), every stage after the depth source.

    The stages (:mod:`omnirecon.mesh.stages`) run in order under one timer (``info["seconds"]``, a stage's name with
    spaces as underscores): ``confidence`` (:func:`~omnirecon.mesh.confidence.prepare`), then the surface
    (``options.surface``): ``fusion`` / ``poisson``: ``fuse`` -> ``marching cubes`` -> ``clean`` -> ``decimate`` ->
    (``poisson``) -> ``complete`` -> (``budget``) (:data:`~omnirecon.mesh.stages.FUSED`); ``coherent``: ``coherent
    surface`` (key ``surface``) -> ``hull trim`` -> ``decimate`` -> ``backdrop`` (:data:`~omnirecon.mesh.stages.COHERENT`);
    then coincident vertices welded (:func:`~omnirecon.mesh.clean.weld`, every face kept in its place).

    Args:
        maps: The depth source's maps (:func:`depth_maps`).
        views: The scene's views the mesh is for: cleaning tests visibility against them and completion
            covers them.
        masks: Object masks of ``scene`` (all its views, ``# [N, H, W]`` bool): carve free space, clean and
            complete inside them (object captures). ``None``: keep the background.
        stages: Filled with the mesh after each stage when given.
        on_stage: Called with the name of each stage as it starts (progress bars).
    """
    if options.surface == "auto":  # the scene kind's, as mesh_from_model's
        options = replace(options, surface=default_surface(scene, masks is not None))
    s = MeshState(maps, scene, list(views), options, masks, device, stages)
    clock = StageClock(on_stage)
    run(COHERENT if options.surface == "coherent" else FUSED, s, clock)
    # the stages' pieces (fused surface, fills, backdrop, closed holes) share the vertices where they coincide; every
    # face keeps its index (completion's record counts faces)
    s.mesh = trimesh.Trimesh(*clean.weld(s.mesh.vertices, s.mesh.faces, keep_faces=True), process=False)
    s.counts["final"] = len(s.mesh.faces)  # what is written: after decimation, hole closing, Poisson and completion
    prep, maps, depth = s.prep, s.maps, s.prep.depth
    info = {"voxel": prep.voxel, "trunc": prep.trunc, "grid": s.surface.get("grid", []), "depth_disagreement": prep.err,
            "consistency_rel": prep.rel, "faces": s.counts, "seconds": clock.seconds, "views": s.views,
            "options": asdict(options), "depth_maps": len(maps.cameras),
            "valid_depth_fraction": float((maps.depth > 0).float().mean()), "masks": masks is not None,
            "depth_source": maps.info, "vertices": len(s.mesh.vertices), "completion": s.completion,
            "mean_weight": float(prep.weight[depth > 0].mean()) if (depth > 0).any() else 0.0,
            "occluded_dropped": prep.occluded, "surface": {k: v for k, v in s.surface.items() if k != "grid"}}
    return MeshResult(s.mesh, info, maps.cameras, maps.depth)


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
    options = resolved(options or MeshOptions(), scene, model is not None, use_masks)
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


def resolved(options: MeshOptions, scene, has_model: bool, masks: bool) -> MeshOptions:
    """``options`` with each ``auto`` made what ``omnirecon mesh`` picks: ``surface`` the scene kind's
    (:func:`default_surface`), ``depth`` its source (:func:`default_depth`), ``depth_pass`` the model's coarse pass for
    ``stereo+model`` (the model only fills stereo's holes), else the fine pass."""
    if options.surface == "auto":
        options = replace(options, surface=default_surface(scene, masks))
    if options.depth == "auto":
        options = replace(options, depth=default_depth(scene, has_model, masks))
    if options.depth_pass == "auto":
        options = replace(options, depth_pass="coarse" if options.depth == "stereo+model" else "fine")
    return options


def default_surface(scene=None, masks: bool = False) -> str:
    """The surface ``omnirecon mesh --surface auto`` (and so ``reconstruct`` and ``demo``) makes: the scene kind's
    (:attr:`omnirecon.scene_kind.SceneKind.surface`: ``coherent`` on a walk, ``fusion`` with completion elsewhere)."""
    return scene_kind(scene, masks).surface


def default_depth(scene=None, has_model: bool = True, masks: bool = False) -> str:
    """The depth source ``omnirecon mesh --depth auto`` (and so ``reconstruct``, ``demo`` and ``MeshOptions()``)
    picks: the scene kind's (:meth:`omnirecon.scene_kind.SceneKind.depth`; ``masks``: meshed with the scene's masks).
    ``stereo`` there is stereo with completion (``MeshOptions.complete``; the bench's ``stereo+fill`` row): on fern it
    scores a little above ``stereo+model`` (``python -m bench depth_sources --rows fern:stereo+fill
    fern:stereo+model``), and on dtu_scan24 / dtu_scan37 over the mask at about the same IoU; on the demo's
    procedural scene ``stereo+model`` scores above ``stereo`` (``--rows demo:stereo+fill demo:stereo+model``), and on
    a 3-view procedural capture stereo alone left most held-out depth uncovered
    (``tests/mesh/test_mesh.py::test_mesh_cli_floor``)."""
    return scene_kind(scene, masks).depth(has_model)
