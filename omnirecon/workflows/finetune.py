"""``omnirecon finetune``: seconds-scale per-scene tuning of the mesh path (``shared/docs/omnirecon.md`` §7).

Size: one workflow: its options (:class:`FinetuneConfig`, one documented field per choice), the run's preparation
(views, mesh, pixels), the tuning loop with its validation and best-state keeping, and the curve, pictures and
record. The pixels and their blend are :mod:`omnirecon.mesh.pixels`' (the mesh path's kernel,
:mod:`omnirecon.mesh.kernel`), the tuner, its sampler and the choice of views :mod:`omnirecon.engine.tuning`'s.

The mesh is fixed (``--mesh`` or extracted from the model at the source views); every training view
of the scene is rasterized once, giving one surface point per covered pixel, and every pixel the mesh
misses a point on the fill's background layer (:func:`omnirecon.mesh.fill.shaded_surface`, as the mesh
renderer does), so every pixel is shaded. Each step samples ``--rays`` shaded pixels of the tuning views
(mesh and fill), colours the points with the appearance branch (``OmniRecon.shade``, over the sources that
see each point: ``--visibility``) from the source views' 2-D encoder features (the feature volume and the
geometry branch are not used by the mesh path and are not computed; the features are encoded once unless the
encoder is tuned) and takes an Adam step on the MSE to the training images. What changes is ``--tune``: the
2-D encoder and the appearance branch by default, optionally a per-source affine colour (``exposure``) or a 3-D
residual colour grid (``residual``), with an L2 pull toward the pretrained weights (``--reg``).

Scoring costs no encoder pass of its own between steps: a validation encodes the sources with their graph and the
next step reuses that pass (its seconds charged to the budget); a returned state is scored on the held-out views
once; the sources' depth is rasterized once for every view group (less process CPU per run, identical held-out
PSNRs).

**Tuning never ends worse than it started.** ``--val-views`` training views (``--val-choice``: by default those
farthest from the other training views, as held-out views are; never blending their own photo) are kept
out of tuning and scored every ``--val-every`` seconds; the state with the best validation gain (the
start is a candidate) is what is returned, saved and scored. A state's validation gain is its gain on what the
scene is scored by (:func:`~omnirecon.engine.tuning.scored_by`: the object pixels on scenes whose protocol scores
the masks, e.g. DTU;
else the whole image); it must reach ``--val-margin`` dB to replace the start, and the other score (whole image
or objects, on scenes with masks) may not drop by more than ``--val-guard`` dB, nor may any one validation view's own
score (``--val-each-view``). The held-out test views (the protocol's
targets) are never tuned on nor used to choose.

The budget is ``--seconds`` of optimisation (``--clock wall``: wall time; ``cpu``: this process's
CPU time, which other jobs on the machine do not shrink). Evaluations do not count against it: at
each of ``--eval-at`` the returned-so-far state renders the held-out views; ``psnr`` is the whole
image, ``psnr_masked`` the object pixels (scenes with masks), ``psnr_covered`` the pixels the mesh
covers (inside the masks) and ``coverage`` the fraction of held-out pixels on real surface.

Outputs in ``--out``: ``curve.json`` (every evaluation: seconds, steps, test and validation PSNR,
coverage), ``curve.png`` (test and validation PSNR against seconds), ``before_after.png`` (GT | before |
after for the first held-out view) and, with ``--save``, the tuned checkpoint.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from omnirecon.data import detect_format
from omnirecon.data.io import write_json
from omnirecon.engine.checkpoint import load_checkpoint, save_checkpoint
from omnirecon.engine.machine import CheckpointInput, ThreadsConfig, set_threads
from omnirecon.engine.protocols import protocol_for, targets_and_pool
from omnirecon.engine.scenes import load_at_resolution, photo_side
from omnirecon.engine.tuning import (
    Clock,
    PixelSampler,
    Setup,
    Tuned,
    Tuner,
    every_training_view,
    pick_validation,
    restrict_to_nearest,
    scored_by,
    validation_gain,
)
from omnirecon.engine.views import check_views, default_views
from omnirecon.errors import InputError
from omnirecon.mesh.build import MeshOptions, mesh_from_model
from omnirecon.mesh.files import read_mesh, write_mesh
from omnirecon.mesh.fill import CRACK_RADIUS
from omnirecon.mesh.ibr import scene_defaults
from omnirecon.mesh.pixels import angle_blend, rasterize_groups, rasterize_views
from omnirecon.options import (
    AdamRate,
    MeshBlend,
    MeshFile,
    OutFolder,
    PhotoSize,
    SceneInput,
    Seeded,
    SourceViews,
    StepRays,
    check_options,
    command_defaults,
)
from omnirecon.preflight import check_memory
from omnirecon.provenance import provenance
from omnirecon.rays import Sources
from omnirecon.render.edges import SOFTEN
from omnirecon.workflows.finetune_curve import plot_curve, write_before_after

EVAL_AT = (0.0, 10.0, 30.0, 60.0, 180.0, 300.0)
"""Default evaluation points (seconds of optimisation; 0 = before tuning)."""


VAL_PIXELS = 8192
"""Validation pixels per validation view (a fixed random subset: scoring stays cheap at any size)."""


@dataclass
@command_defaults(rays=8192)
class FinetuneConfig(OutFolder, Seeded, SourceViews, CheckpointInput, SceneInput, MeshFile, PhotoSize, MeshBlend,
                     StepRays, AdamRate, ThreadsConfig):
    """Tune Omni-Recon's 2-D encoder and appearance branch on one scene's training views through its
    mesh, within a time budget, keeping the best state on validation views; writes a PSNR-vs-time
    curve on the held-out views."""

    seconds: float = 60.0
    """Optimisation budget (see --clock); evaluations are not counted."""
    eval_at: tuple[float, ...] = EVAL_AT
    """Seconds of optimisation at which the held-out views are scored (those beyond --seconds are dropped;
    --seconds itself is always scored)."""
    clock: Literal["wall", "cpu"] = "wall"
    """Budget clock: wall time, or this process's CPU time (fair when other jobs share the machine)."""
    step_views: int = 1
    """Tuning views each step's pixels come from: 1, one view drawn by its shaded pixel count; 0, every tuning view
    in proportion to it (the step's encoder pass covers every source either way, so mixing views costs nothing).
    1 stays the default: 0 raised the demo scene's whole image a little, left fern at the start and lowered
    dtu_scan24's scored objects (`python -m bench finetune_levers`; BENCHMARKS "What fine-tuning tunes, and how far
    it can go")."""
    precision: Literal["fp32", "bf16"] = "fp32"
    """Arithmetic of the tuning steps (`bf16`: autocast; validation and scores stay fp32)."""
    tune: tuple[Literal["encoder", "appearance", "exposure", "residual", "surface"], ...] = ("encoder", "appearance")
    """What is tuned: the 2-D encoder, the appearance branch, and/or `exposure` (a colour gain per source
    view and channel, applied to the source colours the blend mixes; estimated once before tuning, robustly,
    from the tuning views' mesh pixels, and kept only when it beats the input, no gains, on the validation views by
    --val-margin; the record's ``before`` is the input's held-out score). With each pixel's nearest sources (the
    --nearest default) there is little left to tune: the appearance branch alone at 3e-3 raised validation while
    lowering held-out views, so the encoder and the appearance branch at 5e-4 are the default (`python -m bench
    depth_sources`, `python -m bench finetune_levers`; BENCHMARKS "What fine-tuning tunes, and how far it can
    go")."""
    residual_res: int = 16
    """With ``--tune residual``: cells per side of the residual colour grid over the scene's bounds
    (:class:`~omnirecon.mesh.pixels.ResidualColour`: a view-independent colour offset added to the blend at each
    surface point, the same for every view, so what tuning views teach it reaches held-out views at the same surface;
    the only lever under the
    angle blend besides exposure). Not adopted, and not saved with --save: validation returned the start on the demo
    scene, fern and dtu_scan24 under the angle blend, and the demo's state at the end (no validation) raised the
    held-out objects but lowered the whole image (`python -m bench finetune_levers`, rows residual*)."""
    residual_lr: float = 1e-2
    """With ``--tune residual``: the residual grid's Adam learning rate."""
    reg: float = 0.0
    """Weight of the L2 pull of the tuned network weights toward the pretrained ones (mean squared change)."""
    val_views: int = 2
    """Training views kept out of tuning to choose the returned state; 0 = none (the state at the end is
    returned). They are never tuned on and never blend their own photo; under --nearest without --views they stay
    sources of the other views (each view blends only other views' photos), else they are never sources. Keeping
    them among the sources did not lower the held-out score before tuning on the demo scene, fern or dtu_scan24."""
    val_choice: Literal["isolated", "spread"] = "isolated"
    """Which training views validate: `isolated`, one at a time the view farthest from its nearest other training
    view (by angle on object rigs, camera distance otherwise), as held-out views are farther from their sources than
    training views; `spread`, evenly spaced. Under --nearest, `spread` over-promised: the demo scene's evenly spaced
    views gained on validation while its held-out views (which lie where the orbit is sparse) did not, and a short
    run returned a state below the start; `isolated` views are harder than the held-out ones, so nothing that lowers
    them is returned (`python -m bench finetune_validation`; BENCHMARKS "Which views validate fine-tuning")."""
    objects: float = 0.5
    """Scenes with object masks: the fraction of each step's pixels drawn from the mesh pixels inside the masks
    (0: uniform over the shaded pixels; 1: the objects only). 0 gains the whole image a little and the objects not
    at all, so 0.5 stays the default (`python -m bench finetune_levers`; BENCHMARKS "What fine-tuning tunes, and how
    far it can go")."""
    val_margin: float = 0.25
    """A tuned state is returned instead of the start only when its validation gain (on what the scene is
    scored by: the objects on DTU, else the whole image) is at least this many dB: smaller gains on the validation
    views did not carry to held-out views (the demo scene; BENCHMARKS "Which views validate fine-tuning")."""
    val_guard: float = 0.0
    """On scenes with masks, the score the scene is not scored by (the whole image on DTU, the objects on the
    demo) may drop by at most this many dB on validation for a state to be returned (0: never worse on either)."""
    val_each_view: bool = True
    """A tuned state is returned only when each validation view on its own (on what the scene is scored by) drops
    by at most --val-guard dB, besides the views' pooled gain of --val-margin: a state that raises one view and
    lowers another changes what a user sees from some viewpoint for the worse (False: the pooled score alone)."""
    val_every: float = 2.0
    """Seconds of optimisation between validation scores (also scored at every --eval-at)."""
    cracks: int = CRACK_RADIUS
    """Whatever --fill, a pixel the mesh misses but encloses (inside the closing of the covered pixels by a
    ``2 cracks + 1`` square: pinholes and seams between completion's fills) is shaded at the nearest covered pixel's
    z-depth like a mesh point (:func:`omnirecon.mesh.fill.crack_pixels`; 0: off). Coverage still counts only the
    mesh's pixels. Off -> 2 (:data:`~omnirecon.mesh.fill.CRACK_RADIUS`) raised the held-out whole image before tuning
    on the meshes it was tried on (a procedural scene's and the demo scene's stereo+model meshes)."""
    nearest: int = 6
    """Blend at each pixel only the this-many sources nearest the view it renders (by angle on object rigs,
    camera distance otherwise: ``engine.views.select_sources``; a view never blends its own photo), 0 = every
    source. Without --views the sources are then every training view (the validation views too). The nearest
    sources beat 3 fixed ones on every scene tried, 6 slightly beat 4 on fern and the demo scene, and DTU's wide rig
    does slightly better at 4 (`python -m bench depth_sources`; BENCHMARKS "Depth sources")."""
    skip_nearest: int = 0
    """Tuning views blend their --nearest sources after skipping this many nearest (held-out views never skip;
    validation views skip --val-skip): a held-out view lies farther from its sources than a training view from its
    neighbours, so tuning on blends from farther sources was tried as a tuning objective that generalises (`python -m bench
    finetune_levers`, rows skip1 / skip2 / skip1_latest): the demo scene and fern returned the start with 1 and 2,
    so 0 stays the default."""
    val_skip: int = 2
    """Validation views blend their --nearest sources after skipping this many nearest (the network blend; fewer
    skipped when too few sources are left): a view a user looks at lies farther from the photos than a training view
    from its neighbours. Blending its nearest (0), lund's walk gained on validation while the views beyond its end
    lost; from farther sources validation returned the start there and kept the gains of the demo scene and lego
    (`python -m bench finetune_curves`; BENCHMARKS "Fine-tuning curves of the mesh path")."""
    angle_sources: tuple[int, ...] = (3, 4, 6, 8)
    """With the angle blend: sources blended per point. Empty: --nearest; several: the one whose blend scores best on
    the validation views (on what the scene is scored by; nothing is tuned, so this is the angle blend's only
    choice; on dtu_scan24 and dtu_scan37 it chose 4)."""
    consensus: float = 0.0
    """With the angle blend: down-weight each source by how far its colour lies from the blended colour
    (:func:`omnirecon.mesh.kernel.consensus_weights`, a Gaussian of this width in RGB; 0: off)."""
    source_masks: bool = True
    """With the angle blend on real object captures with masks (DTU; :func:`omnirecon.mesh.ibr.masks_hold_scene`):
    each source's weight times
    :func:`omnirecon.mesh.kernel.mask_falloff` at the point's pixel in it (a source whose pixel is its background, or
    within 2 px of it, blends little: the mesh's silhouette overshoots the object's by a pixel or two and took the white
    or black background's colour; the fill's points are not weighed). It raised the held-out mask PSNR on dtu_scan37
    and dtu_scan24 and left the whole image as it was (``python -m bench depth_sources``, the ``, no source masks``
    rows; BENCHMARKS "Depth sources")."""
    soften: float = SOFTEN
    """Blur the rendered colour at the mesh's depth edges by a Gaussian of this many pixels (0: off;
    :func:`omnirecon.render.edges.soften_edges`: a pixel beside an edge the mesh puts a pixel off takes the mean of
    both sides' colours instead of the wrong one; the rest of the image stays sharp), at every held-out score and
    picture (not in the tuning steps nor the validation scores, which sample single pixels). It raises the held-out
    score where the mesh's edges lie about a pixel off (DTU, fern, the demo scene's stereo+model mesh) and costs
    where they are right (the demo's exact mesh: ``--soften 0`` for exact geometry); finetune's validation views do
    not tell the two apart (they are meshed from their own depth). A sigma of 0.5 or 1 px, a blur of the whole image
    and 2x2 supersampling all scored lower on dtu_scan37 (``python -m bench depth_sources``, the ``, no soften``
    rows; BENCHMARKS "Depth sources")."""
    max_held_out: int = 8
    """Held-out views scored at each evaluation (at most this many, evenly spaced over the protocol's targets): 8 scores
    all of DTU's protocol views (0 6 13 19 28 35 42 48; the benches pass 4, scoring 0 13 35 48, unless a row says
    ``, 8 held-out``); fern and the procedural scenes hold out fewer. On DTU the 4 extra views are the harder ones
    (views 19 and 6 of scan37 are darker than the photos around them: the blend cannot know a held-out photo's
    exposure), and they cost rasterizing and scoring 4 more views."""
    split: Literal["protocol", "extrapolation"] = "protocol"
    """The held-out views: the scene's protocol (its test split; DTU's and LLFF's rules), or ``extrapolation``: the test
    views of :func:`omnirecon.engine.protocols.extrapolation_split` (beyond the arc of azimuth the training views
    cover; forward-facing captures and walks: the last stretch of views), every source, tuning and validation view from
    its training views. A ``--mesh`` given with it must be made from those training views alone (``omnirecon mesh
    --views`` with them); without ``--mesh`` the mesh is made from them."""
    save: bool = False
    """Also write the tuned checkpoint to <out>/checkpoint."""
    surface_lr: float = 0.05
    """With ``--tune surface`` (the mesh's vertices moved along their normals by a tuned scalar each, through the
    photometric loss across the sources at the points each pixel's fixed face and barycentrics give:
    :class:`~omnirecon.mesh.offsets.SurfaceOffsets`): the Adam learning rate of the offsets' unbounded parameter
    (``offset = --surface-limit * the scene box's diagonal * tanh(parameter)``). With --save, the returned state's moved mesh
    is written to <out>/mesh.ply (input frame). Not in the default --tune: it moves a planted error back (the test) but
    on stereo meshes of the demo's procedural scene and of fox validation returned the start at every budget
    (`python -m bench finetune_surface`; BENCHMARKS "Tuning the surface")."""
    surface_limit: float = 0.01
    """With ``--tune surface``: the largest offset along a vertex normal, as a fraction of the diagonal of the scene's
    box (the pixels' faces are those of the start mesh: a small bound keeps what they see close to the moved
    mesh's)."""
    surface_res: int = 0
    """With ``--tune surface``: 0, an offset per vertex; R > 0, the offsets a grid of R cells per side over the scene's
    box sampled trilinearly at each vertex (a dense mesh's neighbouring vertices move together; the Laplacian term
    then compares neighbouring cells)."""
    surface_smooth: float = 1.0
    """With ``--tune surface``: weight of the Laplacian term, the mean squared difference of the offsets across the
    mesh's edges in mean edge lengths squared (0: each vertex moves alone)."""
    surface_every: int = 0
    """With ``--tune surface``: rasterize the tuning views again on the moved mesh every this many steps, so their
    faces, points and occlusion test follow the surface (0: never; each pixel keeps the start mesh's face and slides
    along its ray). Validation and held-out views keep the start's faces."""


def split_views(cfg: FinetuneConfig, scene, proto) -> tuple[list[int], list[int], list[int], list[int]]:
    """``(sources, held-out targets, validation views, tuning views)``; refuses sources that are held out."""
    targets, pool = targets_and_pool(proto, scene)
    if cfg.views:
        views = check_views(cfg.views, len(scene), cfg.scene)
    elif cfg.nearest:  # every training view a source (the validation views too: no view blends its own photo)
        views = every_training_view(pool, targets, scene)
    else:
        views = default_views(scene, cfg.num_views)
    held = sorted(set(views) & (set(targets) | set(scene.splits.get("test", []))))
    if held:
        raise InputError(f"--views names held-out view(s) {held}: they are scored, never used as sources", cfg.scene,
                         "pick source views from the training views (`omnirecon inspect` lists the splits)")
    if len(targets) > cfg.max_held_out:
        targets = [targets[i] for i in np.unique(np.linspace(0, len(targets) - 1, cfg.max_held_out).round().astype(int))]
    train_views = [i for i in pool if i not in set(targets) | set(scene.splits.get("test", []))]
    shared = bool(cfg.nearest) and not cfg.views  # validation views are sources of the other views
    val_views = pick_validation(train_views, [] if shared else views, cfg.val_views, scene, cfg.val_choice)
    tune_views = [i for i in train_views if i not in set(val_views) | set(views)] or [
        i for i in train_views if i not in set(val_views)]  # sources are targets only when nothing else is left
    return views, targets, val_views, tune_views


def prepare(cfg: FinetuneConfig, mesh=None, for_run: bool = False) -> Setup:
    """Load the checkpoint and the scene, choose the views, and rasterize the fixed mesh once per view.
    ``for_run`` (:func:`run_finetune`): under the angle blend, with nothing it tunes (no exposure, no residual) no
    tuning view is rasterized, and with several ``--angle-sources`` only the validation views get weights here
    (:func:`choose_angle_sources` sets the others' once, with the chosen count)."""
    model, meta = load_checkpoint(cfg.ckpt)
    if not model.capabilities.appearance:
        raise InputError(f"finetune needs an Omni-Recon checkpoint, got preset {meta['preset']}", cfg.ckpt,
                         "pass checkpoints/omnirecon-tiny or another omnirecon-* checkpoint")
    fmt = detect_format(cfg.scene)
    proto = protocol_for(Path(cfg.scene), fmt)
    if cfg.split == "extrapolation":
        proto = replace(proto, split="extrapolation")
    scene = load_at_resolution(cfg.scene, cfg.resolution or photo_side(cfg.scene, fmt=fmt), proto.background, fmt)
    views, targets, val_views, tune_views = split_views(cfg, scene, proto)
    background = scene.background if scene.background is not None else (
        (0.0,) * 3 if proto.background == "black" else (1.0,) * 3)
    if mesh is None:
        mesh = read_mesh(cfg.mesh, scene.to_input) if cfg.mesh is not None else \
            mesh_from_model(model, scene, views, MeshOptions()).mesh
    if len(mesh.faces) == 0:
        raise InputError("the mesh is empty", cfg.mesh or cfg.ckpt, "check the mesh (or the model's depth)")
    auto_blend, auto_fill = scene_defaults(scene)
    blend, fill_mode = auto_blend if cfg.blend == "auto" else cfg.blend, auto_fill if cfg.fill == "auto" else cfg.fill
    fill = fill_mode in ("far", "nearest")
    vis, near = views if cfg.visibility else None, fill_mode == "nearest"
    idle = for_run and blend == "angle" and not set(cfg.tune) & {"exposure", "residual", "surface"}  # no step samples
    train_px, held_px, val_px = rasterize_groups(mesh, scene, [[] if idle else tune_views, targets, val_views], fill,
                                                 vis, nearest_fill=near, cracks=cfg.cracks,
                                                 faces="surface" in cfg.tune)  # sources' depth once
    train_px = [v for v in train_px if len(v.points)]
    chosen_later = for_run and blend == "angle" and len(cfg.angle_sources) > 1 and bool(val_px)
    for px, skip in ((train_px, cfg.skip_nearest), (held_px, 0), (val_px, cfg.val_skip)):  # the nearest they skip
        if blend == "angle":
            for v in px:
                v.consensus = cfg.consensus
            if chosen_later and px is not val_px:
                continue  # their weights are set once, with the chosen count
            angle_blend(px, scene, views, cfg.angle_sources[0] if cfg.angle_sources else cfg.nearest, cfg.source_masks)
        else:
            restrict_to_nearest(px, scene, views, cfg.nearest, skip)
    if not any(v.covered for v in (val_px + held_px if idle else train_px)):
        raise InputError("the mesh covers no pixel of the training views", cfg.scene, "check the mesh and the poses")
    return Setup(model, meta, scene, views, targets, val_views, Sources.from_scene(scene, views), background, mesh,
                 fill, scored_by(proto, scene), train_px, held_px, val_px, blend, fill_mode)


def curve_point(t_check: float, step: int, r: dict, val: dict, best_val: dict, best_at: tuple[float, int]) -> dict:
    """One evaluation of the curve: test scores ``r`` of the returned state, its validation and the current one."""
    return {"seconds": t_check, "steps": step, "psnr": r["psnr"], "per_view": r["per_view"],
            "val_psnr": best_val["psnr"], "val_psnr_now": val["psnr"],
            **({"val_psnr_masked": best_val["psnr_masked"], "val_psnr_masked_now": val["psnr_masked"]}
               if "psnr_masked" in val else {}),
            "returned_from": {"seconds": best_at[0], "steps": best_at[1]},
            **{k: r[k] for k in ("psnr_masked", "psnr_covered", "coverage", "coverage_masked") if k in r}}


def settle_exposure(cfg: FinetuneConfig, s: Setup, tuner: Tuner, val_idx, val_obj) -> tuple[dict | None, dict | None]:
    """With ``--tune exposure`` and validation views, the estimated gains compete with the input (no gains): kept
    only when they gain ``--val-margin`` on validation. Returns the input's (validation, held-out scores), what
    tuning must beat, or ``(None, None)`` (then the first check's state is the start)."""
    if "exposure" not in cfg.tune or not s.val_px:
        return None, None
    gains = tuner.exposure.gain.detach().clone()
    tuner.set_gains(torch.ones_like(gains))
    start_val, before = tuner.validate(val_idx, val_obj), tuner.test_scores()
    tuner.set_gains(gains)
    gain, guarded = validation_gain(tuner.validate(val_idx, val_obj), start_val, s.scored_by, cfg.val_guard,
                                    cfg.val_each_view)
    if not (gain >= cfg.val_margin and guarded):
        tuner.set_gains(torch.ones_like(gains))
    return start_val, before


def tune(cfg: FinetuneConfig, s: Setup, tuner: Tuner, g: torch.Generator, val_idx: list[torch.Tensor],
         val_obj: list[torch.Tensor] | None = None, on_eval=None) -> Tuned:
    """Tune for ``cfg.seconds``, validating every ``--val-every`` and scoring the held-out views at every
    ``--eval-at`` (then calling ``on_eval(Tuned so far)``); leaves the best state on validation in the model."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    sample = PixelSampler(cfg, s, g)
    eval_at = sorted({float(t) for t in cfg.eval_at if 0 <= t < cfg.seconds} | {0.0, float(cfg.seconds)})
    checks = sorted(set(eval_at) | ({float(t) for t in np.arange(0.0, cfg.seconds, cfg.val_every)}
                                    if tuner.opt is not None else set()))  # nothing tuned: nothing to validate
    curve, validation, step = [], [], 0
    start_val, before = settle_exposure(cfg, s, tuner, val_idx, val_obj)
    best_state, best_val, best_gain, best_at = tuner.state(), {}, -float("inf"), (0.0, 0)
    clock = Clock(cfg.clock)
    columns = (TextColumn("finetune {task.fields[psnr]}"), BarColumn(), TextColumn("{task.completed:.0f}/{task.total:.0f} s"),
               TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn())
    scored = None  # (the returned state's steps, its held-out scores): a state is scored once
    with Progress(*columns) as bar:
        task = bar.add_task("finetune", total=cfg.seconds, psnr="")
        for t_check in checks:
            clock.start()
            while tuner.opt is not None and clock.now() < t_check:
                clock.spent += tuner.step(sample())  # a step's reused encoder pass counts against the budget
                step += 1
                bar.update(task, completed=min(clock.now(), cfg.seconds))
            clock.stop()
            val = validate_once(tuner, validation, step, val_idx, val_obj)
            start_val = start_val or val
            # a state's gain: on what the scene is scored by, the other score guarded (validation_gain)
            gain, guarded = (validation_gain(val, start_val, s.scored_by, cfg.val_guard, cfg.val_each_view)
                             if s.val_px else (0.0, True))
            validation.append({"seconds": t_check, "steps": step, **val, "gain": gain, "guard_ok": guarded})
            if not s.val_px or step == 0 or (gain > best_gain and gain >= cfg.val_margin and guarded):
                best_state, best_val, best_gain, best_at = tuner.state(), val, gain, (t_check, step)  # no validation: the latest
            if t_check not in eval_at:
                continue
            scored = returned_scores(tuner, scored, best_state, best_at[1], step)  # what tuning returns if it stopped here
            r = scored[1]
            before = before or r
            curve.append(curve_point(t_check, step, r, val, best_val, best_at))
            bar.update(task, completed=min(t_check, cfg.seconds), psnr=f"{r['psnr']:.2f} dB")
            if on_eval is not None and t_check < eval_at[-1]:
                on_eval(Tuned(curve, validation, before, r, best_val, best_gain, best_at, step))
    tuner.swap(best_state)  # the returned (and saved) state: the best on validation
    return Tuned(curve, validation, before, r, best_val, best_gain, best_at, step, clock.spent)


def validate_once(tuner: Tuner, validation: list[dict], step: int, val_idx, val_obj) -> dict:
    """The current state's validation scores; the last check's when no step was taken since (the same state)."""
    if validation and validation[-1]["steps"] == step:
        return {k: validation[-1][k] for k in ("psnr", "psnr_masked", "per_view") if k in validation[-1]}
    return tuner.validate(val_idx, val_obj)


def returned_scores(tuner: Tuner, scored: tuple[int, dict] | None, state: list[torch.Tensor], best_step: int,
                    step: int) -> tuple[int, dict]:
    """``(best_step, held-out scores)`` of the returned ``state`` (reached after ``best_step`` steps): ``scored`` when it
    already is that state's, else scored now (the current state's features reused when it is the current one)."""
    if scored is not None and scored[0] == best_step:
        return scored
    if best_step == step:
        return step, tuner.test_scores()
    current = tuner.swap(state)
    r = tuner.test_scores()
    tuner.swap(current)
    return best_step, r


def make_record(cfg: FinetuneConfig, s: Setup, tuner: Tuner, t: Tuned, out: Path) -> dict:
    """The record written to ``curve.json``."""
    result = {"scene": str(cfg.scene), "checkpoint": str(cfg.ckpt), "preset": s.meta["preset"], "sources": s.views,
              "held_out": s.targets, "split": cfg.split, "validation_views": s.val_views, "train_views": len(s.train_px),
              "faces": len(s.mesh.faces), "clock": cfg.clock, "budget_s": cfg.seconds, "rays": cfg.rays, "lr": cfg.lr,
              "reg": cfg.reg, "fill": s.fill_mode,
              "tuned": [t for t in dict.fromkeys(cfg.tune) if s.blend != "angle" or t in ("exposure", "residual",
                                                                                            "surface")],
              "tuned_parameters": sum(p.numel() for p in tuner.params), "resolution": [s.scene.width, s.scene.height],
              "coverage": t.after["coverage"], "curve": t.curve, "validation": t.validation,
              "precision": cfg.precision, "objects": cfg.objects, "val_margin": cfg.val_margin,
              "val_guard": cfg.val_guard, "val_each_view": cfg.val_each_view, "val_skip": cfg.val_skip,
              "val_choice": cfg.val_choice, "nearest": cfg.nearest, "scored_by": s.scored_by,
              "visibility": cfg.visibility, "blend": s.blend,
              **({"angle_sources": s.angle_k or (cfg.angle_sources[0] if cfg.angle_sources else cfg.nearest),
                  "angle_scores": s.angle_scores} if s.blend == "angle" else {}),
              "render": render_record(cfg, s),
              "returned_from": {"seconds": t.best_at[0], "steps": t.best_at[1], "val_psnr": t.best_val["psnr"],
                                "val_gain": t.best_gain},
              "gain_db": t.curve[-1]["psnr"] - t.before["psnr"],
              "before": {k: t.before[k] for k in ("psnr", "psnr_masked", "psnr_covered") if k in t.before},
              "provenance": provenance(seed=cfg.seed), "out": str(out)}
    if tuner.surface is not None:  # the returned state's offsets (scene units; the mean edge length to compare)
        d = tuner.surface.offsets().detach().abs()
        result["surface"] = {"mean_abs_offset": float(d.mean()), "max_abs_offset": float(d.max()),
                             "mean_edge": tuner.surface.edge, "bound": tuner.surface.bound, "limit": cfg.surface_limit,
                             "lr": cfg.surface_lr, "smooth": cfg.surface_smooth, "res": cfg.surface_res,
                             "every": cfg.surface_every}
    if "exposure" in cfg.tune:
        result["exposure"] = {"gain": tuner.exposure.gain.detach().reshape(-1, 3).tolist(),
                              "offset": tuner.exposure.offset.detach().reshape(-1, 3).tolist()}
    return result


def render_record(cfg: FinetuneConfig, s: Setup) -> dict:
    """What the scores blended with, for the real-time mesh path to blend alike
    (:func:`omnirecon.mesh.ibr.realtime_setting`): the blend, the fill, the sources per view (the network's blend under
    ``--nearest``: the view's nearest training views; the angle blend: every source, each point picking its nearest
    among them; else the fixed ``sources`` count), the angle blend's sources per point (the validation choice) and
    whether sources were weighted by their masks, the cracks' radius and the blur at depth edges (``--soften``)."""
    from omnirecon.mesh.ibr import masks_hold_scene

    k = s.angle_k or (cfg.angle_sources[0] if cfg.angle_sources else cfg.nearest)
    per_view = cfg.nearest if cfg.nearest and not cfg.views and s.blend != "angle" else len(s.views)
    return {"blend": s.blend, "fill": s.fill_mode, "sources": per_view, "angle_sources": k,
            "source_masks": cfg.source_masks and masks_hold_scene(s.scene), "cracks": cfg.cracks, "soften": cfg.soften}


def choose_angle_sources(cfg: FinetuneConfig, s: Setup, tuner: Tuner, val_idx, val_obj) -> int:
    """``--angle-sources`` with several values: the one whose angle blend scores best on the validation views (on
    what the scene is scored by); every view's weights are then set with it. Returns it."""
    key = "psnr_masked" if s.scored_by == "objects" and val_obj is not None else "psnr"
    scores = {}
    for k in cfg.angle_sources:
        angle_blend(s.val_px, s.scene, s.views, k, cfg.source_masks)
        scores[k] = tuner.validate(val_idx, val_obj).get(key, float("nan"))
    best = max(scores, key=lambda k: (scores[k], -k))
    for px in (s.train_px, s.held_px, s.val_px):
        angle_blend(px, s.scene, s.views, best, cfg.source_masks)
    s.angle_scores = scores
    return best


def retrace_training(cfg: FinetuneConfig, s: Setup):
    """``--surface-every``: a moved mesh -> the tuning views' pixels on it, blended as :func:`prepare` blends them
    (their faces and barycentrics located, the occlusion test against the moved mesh)."""
    def retrace(mesh) -> list:
        px = rasterize_views(mesh, s.scene, [v.index for v in s.train_px], s.fill, s.views if cfg.visibility else None,
                             nearest_fill=s.fill_mode == "nearest", cracks=cfg.cracks, faces=True)
        px = [v for v in px if len(v.points)]
        if s.blend == "angle":
            for v in px:
                v.consensus = cfg.consensus
            angle_blend(px, s.scene, s.views, s.angle_k or (cfg.angle_sources[0] if cfg.angle_sources else cfg.nearest),
                        cfg.source_masks)
        else:
            restrict_to_nearest(px, s.scene, s.views, cfg.nearest, cfg.skip_nearest)
        return px
    return retrace


def cpu_split(cpu: dict, budget: float, end: float) -> dict:
    """This run's process CPU-seconds: ``prepare`` (loading, rasterizing), ``budget`` (the tuning steps, on
    ``--clock cpu`` the budget itself), ``outside_budget`` (validation and held-out scores, pictures and records),
    ``process`` (everything since the process started, imports too)."""
    return {"prepare": cpu["prepared"] - cpu["start"], "budget": budget,
            "outside_budget": end - cpu["prepared"] - budget, "process": end}


def held_out_defects(s: Setup, fill_from: int | None = None) -> dict:
    """Mean over the held-out views of the share of their pixels drawn by faces no photo supports
    (:mod:`omnirecon.mesh.defects`: completion's fills, the faces from ``fill_from`` on when known; faces no source
    view sees; fragments), by kind and in all (``any``): what a viewer sees away from the photos."""
    from omnirecon.mesh.defects import DefectCounter

    cams = s.scene.cameras
    with DefectCounter(s.mesh, cams[s.views], s.scene.bounds, fill_from) as counter:
        shares = [counter(cams[v]) for v in s.targets]
    return {k: round(float(np.mean([d[k] for d in shares])), 4) for k in shares[0]} if shares else {}


def run_finetune(cfg: FinetuneConfig, mesh=None, fill_from: int | None = None) -> dict:
    """Run ``omnirecon finetune``; returns ``{"out", "curve", ...}`` as written to ``curve.json``. ``mesh``: a
    ``trimesh.Trimesh`` in the scene frame, handed over in memory (``reconstruct``), instead of ``cfg.mesh``, with
    completion's fills as its faces from ``fill_from`` on (for the defect shares; ``None``: no fills known)."""
    check_options("finetune", cfg)  # the numbers (omnirecon/options.py); here for callers other than the CLI
    if not cfg.tune:
        raise InputError("--tune names nothing to tune", None, "use e.g. --tune encoder appearance")
    # the validation times (one every --val-every seconds): an array and a set of floats, about 120 bytes each
    check_memory(cfg.seconds / cfg.val_every * 120, "--val-every", lambda share: f"{cfg.val_every / share:.2g}")
    set_threads(cfg.threads)
    cpu = {"start": time.process_time()}
    s = prepare(cfg, mesh, for_run=True)
    cpu["prepared"] = time.process_time()
    out = Path(cfg.out or Path("outputs/finetune") / Path(cfg.scene).name)
    g = torch.Generator().manual_seed(cfg.seed)
    val_idx = [torch.randperm(len(v.points), generator=g)[:VAL_PIXELS] for v in s.val_px]
    val_obj = None if s.scene.masks is None else [s.scene.masks[v.index].reshape(-1).bool()[v.pixels[i]]
                                                   for v, i in zip(s.val_px, val_idx)]  # validation pixels on the objects
    tuner = Tuner(cfg, s, g)
    if s.blend == "angle" and len(cfg.angle_sources) > 1 and s.val_px:
        s.angle_k = choose_angle_sources(cfg, s, tuner, val_idx, val_obj)
    tuner.retrace = retrace_training(cfg, s) if tuner.surface is not None else None

    def write(t: Tuned, partial: bool = False) -> dict:  # at every evaluation: an interrupted run keeps its curve
        plot_curve(cfg, s, t, out)
        write_before_after(s, t, out)
        result = make_record(cfg, s, tuner, t, out)
        write_json(out / "curve.json", {**result, **({"partial": True} if partial else {})})
        return result

    tuned = tune(cfg, s, tuner, g, val_idx, val_obj, on_eval=lambda t: write(t, partial=True))
    cpu["tuned"] = time.process_time()
    result = write(tuned)
    result["defects"] = held_out_defects(s, fill_from)
    result["cpu_seconds"] = cpu_split(cpu, tuned.budget_spent, time.process_time())
    write_json(out / "curve.json", result)
    if cfg.save and tuner.surface is not None:  # the returned state's surface, in the input frame
        write_mesh(tuner.surface.moved(s.mesh), [out / "mesh.ply"], s.scene.to_input)
    if cfg.save:
        save_checkpoint(out / "checkpoint", s.model, s.meta["preset"], step=tuned.steps,
                        extra={"finetuned_on": str(cfg.scene), "seconds": cfg.seconds,
                               "returned_from": result["returned_from"], **({"exposure": result["exposure"]}
                                                                            if "exposure" in result else {})})
    return result
