"""The stages of the mesh pipeline after the depth source (:func:`omnirecon.mesh.build.mesh_from_depths`): each a
small function over one :class:`MeshState`, named in a list (:data:`FUSED`, :data:`COHERENT`), run in order by
:func:`run` under one :class:`StageClock`.

* :data:`FUSED` (``--surface fusion`` / ``poisson``): ``confidence`` -> ``fuse`` -> ``marching cubes`` -> ``clean``
  (hidden faces, small components, visual-hull trim) -> ``decimate`` (face budget, small holes closed) ->
  (``poisson``) -> ``complete`` -> ``budget`` when the fills pushed the mesh over it (:func:`refit`: the fused
  surface decimated to what they leave, and the fills made again on it).
* :data:`COHERENT`: ``confidence`` -> (the fused surface as its fine surface: ``fuse``, ``clean``) -> ``coherent
  surface`` -> ``hull trim`` -> ``decimate`` -> ``backdrop`` (forward-facing scenes). No fill is made.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch
import trimesh
from torch import Tensor

from omnirecon.errors import InputError
from omnirecon.mesh import clean, fusion
from omnirecon.mesh.complete import complete_surface
from omnirecon.mesh.confidence import Prepared, prepare
from omnirecon.mesh.depth import DepthMaps
from omnirecon.scene_kind import SceneKind, scene_kind

if TYPE_CHECKING:
    from omnirecon.mesh.build import MeshOptions


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
class MeshState:
    """What the stages share: the inputs of :func:`~omnirecon.mesh.build.mesh_from_depths`, then each stage's
    result."""

    maps: DepthMaps
    """The depth source's maps; after ``confidence`` without the known background's pixels (what completion reads)."""
    scene: object
    """The :class:`~omnirecon.data.scene.Scene` (normalised frame)."""
    views: list[int]
    """The views the mesh is cleaned against and completed at."""
    options: MeshOptions
    masks: Tensor | None
    """Object masks of every view of the scene (``None``: keep the background). ``# [V, H, W]`` bool"""
    device: str = "cpu"
    """Where fusion runs."""
    keep: dict | None = None
    """Filled with the mesh after each stage when given (``mesh_from_depths(stages=...)``)."""
    prep: Prepared | None = None
    """The confidence stage's depth, weights, evidence and scales."""
    volume: Tensor | None = None
    """The fused TSDF (``fuse``)."""
    mesh: trimesh.Trimesh | None = None
    """The mesh so far (scene frame)."""
    fused: trimesh.Trimesh | None = None
    """The fused surface: with :data:`FUSED`, cleaned and within the face budget (what Poisson and completion start
    from); with :data:`COHERENT`, the cleaned TSDF surface the coherent surface takes as its fine surface."""
    counts: dict = field(default_factory=dict)
    """Face counts after each stage."""
    completion: dict | None = None
    """Completion's record (or the backdrop's)."""
    surface: dict = field(default_factory=dict)
    """The surface's record (``grid``: the TSDF's shape; the coherent surface's record)."""

    def stage_done(self, name: str, mesh: trimesh.Trimesh | None = None) -> None:
        """Keep ``mesh`` (default: the mesh so far) as stage ``name``'s when the caller asked for them."""
        if self.keep is not None:
            self.keep[name] = self.mesh if mesh is None else mesh

    @cached_property
    def view_cams(self):
        """The cameras of ``views``, float64."""
        return self.scene.cameras[self.views].to(dtype=torch.float64)

    @property
    def view_masks(self) -> np.ndarray | None:
        """The dilated masks of ``views`` (cleaning's, Poisson's and completion's). ``# [len(views), H, W]`` bool"""
        return None if self.prep.dilated is None else self.prep.dilated[self.views].numpy()

    @cached_property
    def hull(self) -> np.ndarray | None:
        """The masks of ``views`` dilated for the visual-hull trim, or ``None`` (no masks, or the trim is off)."""
        if self.masks is None or self.options.hull_misses < 0:
            return None
        return clean.dilate_masks(self.masks[self.views].cpu().numpy().astype(bool),
                                  self.options.hull_dilate * self.scene.width)

    @cached_property
    def kind(self) -> SceneKind:
        """The scene's kind, with ``masks`` as given (it picks the stages' scene-dependent steps)."""
        return scene_kind(self.scene, self.masks is not None)


@dataclass(frozen=True)
class Stage:
    """One named stage of the pipeline."""

    name: str
    """What ``on_stage`` announces; its seconds go to ``key`` (default: the name with spaces as underscores)."""
    run: Callable[[MeshState], list[Stage] | None]
    """The stage: updates the state; may return stages to run next (the face budget's second pass)."""
    when: Callable[[MeshState], bool] = lambda s: True
    """Whether it runs (asked when its turn comes)."""
    key: str | None = None


def run(stages: list[Stage], state: MeshState, clock: StageClock) -> None:
    """Each of ``stages`` that runs (:attr:`Stage.when`) timed by ``clock``, then the stages it returns."""
    for stage in stages:
        if stage.when(state):
            with clock(stage.name, stage.key):
                more = stage.run(state)
            if more:
                run(more, state, clock)


# ---------------------------------------------------------------------- shared stages
def confidence(s: MeshState) -> None:
    """Depth, weights and evidence for fusion (:func:`~omnirecon.mesh.confidence.prepare`)."""
    s.prep, s.maps = prepare(s.maps, s.scene, s.options, s.masks, s.kind)
    if s.options.surface == "coherent" and s.prep.agree is None:
        raise InputError("the coherent surface needs at least two depth maps to confirm each other", s.scene.path,
                         "mesh from more views, or use --surface fusion")


def cull_samples(s: MeshState) -> int:
    """Hidden-face test samples per pixel side: ``options.cull_samples`` per voxel edge at the median depth."""
    o = s.options
    return int(np.clip(np.ceil(o.cull_samples * s.prep.footprint / s.prep.voxel), 1, max(1, int(2 * o.cull_samples))))


def fuse(s: MeshState) -> None:
    """TSDF fusion of the confident depth over the scene bounds."""
    p, o = s.prep, s.options
    s.volume = fusion.fuse(p.cams, p.depth, s.scene.bounds, p.voxel, p.trunc, p.weight, p.free, o.voxel_chunk,
                           o.bilinear, s.device, band=o.band)
    s.surface = {"grid": list(s.volume.shape)}


def marching_cubes(s: MeshState) -> None:
    s.mesh = fusion.extract_mesh(s.volume)
    s.counts["marching_cubes"] = len(s.mesh.faces)
    s.stage_done("marching_cubes")


def clean_fused(s: MeshState) -> None:
    """Mask votes, hidden faces, small components (:func:`clean.clean_mesh`), then the visual-hull trim."""
    s.mesh, cleaned = clean.clean_mesh(s.mesh, s.view_cams, s.view_masks, s.options, cull_samples(s), s.keep)
    s.counts.update(cleaned)
    if s.hull is not None:
        s.mesh = clean.hull_trim(s.mesh, s.view_cams, s.hull, s.options.hull_misses)
        s.counts["hull"] = len(s.mesh.faces)


def decimate_fused(s: MeshState) -> None:
    """The face budget, then small holes closed (:func:`within_budget`)."""
    s.fused = s.mesh = within_budget(s.mesh, s.options.max_faces, s.options, s.counts, s.kind.object_without_masks)
    s.stage_done("decimated")


def poisson(s: MeshState) -> None:
    """Screened Poisson over the fused surface, trimmed to the masks (:mod:`omnirecon.mesh.poisson`)."""
    from omnirecon.mesh.poisson import poisson_surface

    s.mesh, s.counts["poisson"] = poisson_surface(s.mesh, s.view_cams, s.view_masks)
    s.stage_done("poisson")


def complete(s: MeshState) -> None:
    """Completion (:func:`complete_surface`), then the visual-hull trim of the fills."""
    s.mesh, s.completion = completed(s)
    s.stage_done("completed")


FILLS = [Stage("poisson", poisson, when=lambda s: s.options.surface == "poisson" and s.prep.dilated is not None),
         Stage("complete", complete, when=lambda s: s.options.complete)]
"""What comes after the fused surface's face budget: made again when the budget is refitted (:func:`refit`)."""


def over_budget(s: MeshState) -> bool:
    return bool(s.options.max_faces) and len(s.mesh.faces) > s.options.max_faces


def refit(s: MeshState) -> list[Stage]:
    """The completed mesh over ``options.max_faces``: the fused surface gets what completion leaves of the budget and
    the fills are made again on it (they match the surface that is written); then :func:`trim_fused`. Without this a
    budget held only the fused surface, and the fills and a backdrop came on top of it; decimating the completed mesh
    as a whole instead scored lower on fern's held-out views (``python -m bench depth_sources --rows "fern:stereo+fill,
    nearest 6"``; face counts and scores per budget: BENCHMARKS "Depth sources", "Real-time mesh path")."""
    budget = s.options.max_faces
    extra = len(s.mesh.faces) - len(s.fused.faces)  # completion's faces (and Poisson's change)
    added = len(s.fused.faces) - s.counts["decimated"]  # the hole closers' faces
    room = budget - extra - added - budget // 50  # a margin: the fills of a coarser surface differ a little
    s.counts["over_budget"] = len(s.mesh.faces)
    if room < budget // 4:  # the fused surface keeps at least a quarter of the budget
        trim_fused(s)
        return []
    s.fused = s.mesh = within_budget(s.fused, room, s.options, s.counts, s.kind.object_without_masks)
    s.completion = None
    return [*FILLS, Stage("budget", trim_fused)]


def trim_fused(s: MeshState) -> None:
    """A last small overshoot of the budget (the coarser surface needs a few more fills) comes off the fused part."""
    budget, mesh = s.options.max_faces, s.mesh
    if len(mesh.faces) > budget:  # still over: trim the fused part only (it comes first)
        n = s.completion["surface_faces"] if s.completion is not None else 0
        rest = len(mesh.faces) - n
        if n > 0 and budget - rest >= budget // 8:
            part = clean.decimate(trimesh.Trimesh(mesh.vertices, mesh.faces[:n], process=False), budget - rest)
            fills = trimesh.Trimesh(mesh.vertices, mesh.faces[n:], process=False)
            fills.remove_unreferenced_vertices()
            mesh = trimesh.util.concatenate([part, fills])
        else:  # the fills alone fill the budget (or the order is unknown): decimate everything
            mesh = clean.decimate(mesh, budget)
    s.mesh = mesh
    s.counts["budgeted"] = len(mesh.faces)


FUSED = [Stage("confidence", confidence), Stage("fuse", fuse), Stage("marching cubes", marching_cubes),
         Stage("clean", clean_fused), Stage("decimate", decimate_fused), *FILLS,
         Stage("budget", refit, when=over_budget)]
"""The fused surface's stages (``--surface fusion`` and ``poisson``)."""


# ---------------------------------------------------------------------- the coherent surface
def fine_tsdf(s: MeshState) -> bool:
    return s.options.coherent.fine == "tsdf"


def fuse_fine(s: MeshState) -> None:
    """The fused TSDF surface as the coherent surface's fine surface."""
    p, o = s.prep, s.options
    volume = fusion.fuse(p.cams, p.depth, s.scene.bounds, p.voxel, p.trunc, p.weight, p.free, o.voxel_chunk,
                         o.bilinear, "cpu", band=o.band)
    s.fused = fusion.extract_mesh(volume)


def clean_fine(s: MeshState) -> None:
    s.fused, _ = clean.clean_mesh(s.fused, s.view_cams, s.view_masks, s.options, cull_samples(s))


def coherent(s: MeshState) -> None:
    """One surface from the depth several views confirm (:mod:`omnirecon.mesh.surface`)."""
    from omnirecon.mesh.surface import coherent_surface

    p, o = s.prep, s.options
    s.mesh, s.surface = coherent_surface(p.cams, p.unbounded, p.agree, p.voxel, p.rel, s.scene.bounds, p.empty,
                                         o.coherent, o.min_component, s.fused)
    s.counts["coherent"] = len(s.mesh.faces)
    s.stage_done("coherent")


def hull_trim(s: MeshState) -> None:
    s.mesh = clean.hull_trim(s.mesh, s.view_cams, s.hull, s.options.hull_misses)
    s.counts["hull"] = len(s.mesh.faces)


def decimate(s: MeshState) -> None:
    s.mesh = clean.decimate(s.mesh, s.options.max_faces)
    s.counts["decimated"] = len(s.mesh.faces)
    s.stage_done("completed")


def backdrop(s: MeshState) -> None:
    """A forward-facing scene's background layer: the bounds' far side (:func:`complete.backdrop_sheet`)."""
    from omnirecon.mesh.complete import backdrop_sheet

    sheet = backdrop_sheet(s.view_cams, s.scene.bounds, s.options.backdrop_pad)
    s.completion = {"backdrop_faces": len(sheet.faces), "surface_faces": len(s.mesh.faces), "fill_faces": 0}
    s.mesh = trimesh.util.concatenate([s.mesh, sheet]) if len(sheet.faces) else s.mesh
    s.stage_done("completed")


COHERENT = [Stage("confidence", confidence), Stage("fuse", fuse_fine, when=fine_tsdf),
            Stage("clean", clean_fine, when=fine_tsdf), Stage("coherent surface", coherent, key="surface"),
            Stage("hull trim", hull_trim, when=lambda s: s.hull is not None), Stage("decimate", decimate),
            Stage("backdrop", backdrop, when=lambda s: s.kind.forward and s.options.backdrop_pad >= 0)]
"""The coherent surface's stages (``--surface coherent``)."""


# ---------------------------------------------------------------------- helpers
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




def completed(s: MeshState) -> tuple[trimesh.Trimesh, dict]:
    """Completion (:func:`complete_surface`) of the mesh so far at ``s.views``, then the visual-hull trim of the
    fills: ``(mesh, completion's record)``."""
    mesh, prep, scene, options, masks = s.mesh, s.prep, s.scene, s.options, s.masks
    view_depths = completion_depths(s.maps, s.views, options, prep.agree if s.kind.confirmed_fill else None)
    content = None if not s.kind.content_fill or options.content_fill <= 0 else \
        content_pixels(scene, s.views, options.content_fill, view_depths)
    surface = len(mesh.faces)
    mesh, completion = complete_surface(mesh, s.view_cams, view_depths, scene.bounds, s.view_masks,
                                        forward=s.kind.forward, occlusion_rel=prep.rel if options.fill_occlusion and masks is None else None,
                                        backdrop_pad=options.backdrop_pad, content=content)
    if s.hull is not None:  # fills from a view's own depth obey the other views' silhouettes too
        keep = clean.hull_keep(mesh, s.view_cams, s.hull, options.hull_misses)
        if options.hull_keeps_seen:  # but never what a training view sees and nothing else covers
            keep = clean.restore_seen(mesh, keep, s.view_cams, masks[s.views].cpu().numpy().astype(bool))
        mesh, surface = clean.keep_faces(mesh, keep), int(keep[:surface].sum())
    completion["surface_faces"] = surface  # the fused (or Poisson) surface's faces come first
    s.counts["completed"] = len(mesh.faces)
    return mesh, completion


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

