"""``omnirecon finetune``'s tuning pieces below the workflow: which views tune, validate and blend which sources
(:func:`pick_validation`, :func:`nearest_blend`, :func:`restrict_to_nearest`), what one run tunes on (:class:`Setup`),
the tuned parameters with their optimiser and scores (:class:`Tuner`), each step's pixels (:class:`PixelSampler`) and
the budget's clock (:class:`Clock`). The pixels and their blend are :mod:`omnirecon.mesh.pixels`' (the mesh path's
kernel, :mod:`omnirecon.mesh.kernel`, with gradients on).

Size: one concern, what a tuning step changes and on which pixels: the tuner with every lever (networks, exposure,
residual colour, the surface's offsets and their re-rasterization), its sampler and the choice of views.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import torch

from omnirecon.engine.views import select_sources
from omnirecon.mesh.offsets import SurfaceOffsets
from omnirecon.mesh.pixels import (
    Exposure,
    ResidualColour,
    ViewPixels,
    encode_maps,
    estimate_gains,
    point_colours,
    render_pixels,
    score_held_out,
    visible_at,
)
from omnirecon.models.omnirecon import OmniReconFeatures
from omnirecon.rays import Sources


class Clock:
    """Seconds of optimisation on the chosen clock, paused while evaluating."""

    def __init__(self, kind: str):
        self.read = time.perf_counter if kind == "wall" else time.process_time
        self.spent = 0.0
        self._start = None

    def start(self) -> None:
        self._start = self.read()

    def stop(self) -> None:
        self.spent += self.read() - self._start
        self._start = None

    def now(self) -> float:
        return self.spent + (self.read() - self._start if self._start is not None else 0.0)


def every_training_view(pool: list[int], targets: list[int], scene) -> list[int]:
    """The sources of ``--nearest`` without ``--views``: every training view (the protocol's pool, never a
    held-out or test view), the validation views too (each view blends only the other views' photos)."""
    return [i for i in pool if i not in set(targets) | set(scene.splits.get("test", []))]


def nearest_blend(scene, view: int, sources: list[int], k: int, skip: int = 0) -> torch.Tensor:
    """Which of ``sources`` view ``view`` blends under ``--nearest k``: the ``k`` nearest to it, never
    ``view`` itself (a tuning view that is also a source learns from the others); with ``skip``, the ``k`` after the
    ``skip`` nearest (fewer skipped when too few sources are left). ``# [K]`` bool"""
    others = [s for s in sources if s != view]
    near = select_sources(scene, scene.cameras[view], others, min(k + skip, len(others))) if others else []
    keep = set(near[max(0, len(near) - k):])
    return torch.tensor([s in keep for s in sources], dtype=torch.bool)


def restrict_to_nearest(pixels: list[ViewPixels], scene, sources: list[int], k: int, skip: int = 0) -> None:
    """Mask every pixel of each view in ``pixels`` to its :func:`nearest_blend` sources (in place; ``k`` = 0:
    unchanged). A point the occlusion test hides from all of them blends those ``k`` (not every source)."""
    if k <= 0:
        return
    for v in pixels:
        near = nearest_blend(scene, v.index, sources, k, skip)  # [K]
        vis = v.visible if v.visible is not None else torch.ones(len(v.points), len(sources), dtype=torch.bool)
        vis = vis & near  # [P, K]
        vis[~vis.any(-1)] = near
        v.visible = vis


def pick_validation(train_views: list[int], sources: list[int], n: int, scene=None,
                    how: str = "spread") -> list[int]:
    """``n`` training views, never one of ``sources``; always leaves a view to tune on. ``how`` (``--val-choice``):
    ``spread``, evenly spaced; ``isolated`` (needs ``scene``), one at a time the candidate farthest from its nearest
    other training view not yet chosen."""
    cand = [i for i in train_views if i not in set(sources)]
    n = min(n, len(cand), len(train_views) - 1)
    if n < 1:
        return []
    if how == "isolated":
        return isolated_views(scene, train_views, cand, n)
    return [cand[i] for i in np.unique(np.linspace(0, len(cand) - 1, n + 2).round().astype(int))[1:-1][:n]] or cand[:n]


def isolated_views(scene, train_views: list[int], cand: list[int], n: int) -> list[int]:
    """``n`` of ``cand``, greedily the one whose nearest other remaining training view is farthest (by angle about
    the look-at centre on object rigs, camera distance otherwise: ``engine.views.view_metric``)."""
    from omnirecon.cameras import closest_point_to_axes, view_distances
    from omnirecon.engine.views import view_metric

    by = view_metric(scene)
    cams = scene.cameras[train_views]
    d = view_distances(cams, cams, by=by, center=closest_point_to_axes(scene.cameras) if by == "angle" else None)
    d = d.double().clone().fill_diagonal_(float("inf"))  # [T, T]
    left, chosen = list(range(len(train_views))), []
    for _ in range(n):
        score = {j: float(d[j, [m for m in left if m != j]].min()) for j in left if train_views[j] in set(cand)}
        best = max(score, key=lambda j: (score[j], -j))
        chosen.append(train_views[best])
        left.remove(best)
    return sorted(chosen)


@dataclass
class Setup:
    """What one run tunes on: the model, the scene, its views, and the mesh's pixels per view."""

    model: torch.nn.Module
    meta: dict
    scene: object
    views: list[int]
    """Source views."""
    targets: list[int]
    """Held-out views scored at each evaluation."""
    val_views: list[int]
    """Training views kept out of tuning to choose the returned state."""
    sources: Sources
    background: tuple[float, float, float]
    mesh: object
    """The fixed mesh, scene frame (``trimesh.Trimesh``)."""
    fill: bool
    scored_by: str
    """``"objects"`` (the protocol scores the object masks and the scene has them) or ``"image"``."""
    train_px: list[ViewPixels]
    held_px: list[ViewPixels]
    val_px: list[ViewPixels]
    blend: str = "network"
    """``--blend``, ``auto`` resolved (:func:`omnirecon.mesh.ibr.scene_blend`)."""
    fill_mode: str = "far"
    """``--fill``, ``auto`` resolved: ``far``, ``nearest`` or ``background``."""
    angle_k: int = 0
    """With the angle blend: sources per point (``--angle-sources`` or ``--nearest``)."""
    angle_scores: dict | None = None
    """With several ``--angle-sources``: the validation score of each."""


def scored_by(proto, scene) -> str:
    """What the scene's results are scored by: ``"objects"`` when its protocol scores the object masks
    (``Protocol.masked``: DTU, Blender) and it has them, else ``"image"``."""
    return "objects" if proto.masked and scene.masks is not None else "image"


def validation_gain(val: dict, start: dict, scored: str, guard: float, each_view: bool = False) -> tuple[float, bool]:
    """A state's validation gain over the start on what the scene is scored by (``psnr_masked`` for
    ``scored == "objects"`` when measured, else ``psnr``), and whether every other score dropped by at most
    ``guard`` dB; with ``each_view``, also each validation view's own score (``per_view``: on what the scene is
    scored by) by at most ``guard`` dB."""
    key = "psnr_masked" if scored == "objects" and "psnr_masked" in val else "psnr"
    gain = val[key] - start[key]
    guarded = all(val[k] - start[k] >= -guard for k in val if k not in (key, "per_view"))
    if each_view and "per_view" in val and "per_view" in start:
        guarded = guarded and all(v - s >= -guard for v, s in zip(val["per_view"], start["per_view"]))
    return gain, guarded


def psnr_of(se: torch.Tensor) -> float:
    """PSNR in dB of the mean of per-pixel squared errors ``se`` (colours in [0, 1]). ``se``: ``# [P]``"""
    return float(-10 * torch.log10(se.mean().clamp_min(1e-10)))


class Tuner:
    """The tuned parameters of one run, their optimiser and exposure, and the scores of their current state.
    ``cfg``: the run's ``FinetuneConfig`` (``tune``, ``lr``, ``reg``, ``precision``, ``clock``, ...)."""

    def __init__(self, cfg, s: Setup, g: torch.Generator):
        self.s, self.reg, model, self.consensus = s, cfg.reg, s.model, cfg.consensus
        self.soften = cfg.soften
        """``--soften``: the held-out renders' blur at the mesh's depth edges (px)."""
        self.exposure = Exposure(len(s.views))
        modules = {"encoder": model.encoder, "appearance": model.appearance}
        nets = [] if s.blend == "angle" else [  # the angle blend uses neither network
            p for name in dict.fromkeys(cfg.tune) if name in modules for p in modules[name].parameters()]
        self.residual = ResidualColour(s.scene.bounds, cfg.residual_res) if "residual" in cfg.tune else None
        self.surface = SurfaceOffsets(s.mesh, cfg.surface_limit, s.scene.bounds, cfg.surface_res) if "surface" in cfg.tune else None
        """``--tune surface``: the mesh's per-vertex offsets along its normals (``None``: the surface is fixed)."""
        self.smooth = cfg.surface_smooth
        self.retrace = None
        """With ``--surface-every``: a moved mesh -> the tuning views' pixels rasterized on it (set by the workflow)."""
        self.every, self.steps = cfg.surface_every, 0
        self.base = None
        """The offsets the tuning views were last rasterized at (``None``: the start mesh). ``# [V]``"""
        self.params = nets + ([self.residual.grid] if self.residual is not None else []) + (
            [self.surface.raw] if self.surface is not None else [])
        self.start = [p.detach().clone() for p in self.params]
        if "exposure" in cfg.tune:
            with torch.no_grad():
                self.exposure.gain.copy_(estimate_gains(model, s.sources, s.train_px, g))
        for p in model.parameters():
            p.requires_grad_(False)
        for p in self.params:
            p.requires_grad_(True)
        groups = [g for g in ({"params": nets, "lr": cfg.lr},
                              {"params": [self.residual.grid] if self.residual is not None else [],
                               "lr": cfg.residual_lr},
                              {"params": [self.surface.raw] if self.surface is not None else [],
                               "lr": cfg.surface_lr}) if g["params"]]
        self.opt = torch.optim.Adam(groups) if groups else None
        model.train()
        self.exposed = "exposure" in cfg.tune
        """Whether the blend mixes exposure-corrected colours (else the photos as they are: no identity pass)."""
        self.frozen = None
        """The features when the encoder is not tuned (they do not change: encoded once)."""
        if "encoder" not in cfg.tune or s.blend == "angle":  # the encoder is not tuned: encoded once
            with torch.no_grad():
                self.frozen = self.features()
        self.autocast = torch.autocast(device_type="cpu", dtype=torch.bfloat16, enabled=cfg.precision == "bf16")
        self.pending = None
        """The features of the current state with their graph, encoded for a score: the next step reuses them
        (fp32 only: a bf16 step encodes under autocast) and charges ``pending_cost`` to the budget."""
        self.pending_cost = 0.0
        self.reuse = (cfg.precision == "fp32" and self.frozen is None and not any(  # eval-mode BN would differ
            getattr(m, "track_running_stats", False) for m in model.encoder.modules())
            and not 0 < cfg.nearest < len(s.views))  # a step encodes only the sources it blends (used_sources)
        self.read = time.perf_counter if cfg.clock == "wall" else time.process_time

    def set_gains(self, gain: torch.Tensor) -> None:
        """Load exposure gains ``# [K, 1, 1, 3]`` (re-encoding the frozen features that mix them)."""
        self.pending, self.pending_cost = None, 0.0  # encoded with the old gains
        with torch.no_grad():
            self.exposure.gain.copy_(gain)
            if self.frozen is not None:
                self.frozen = self.features()

    def features(self, keep: torch.Tensor | None = None):
        """The sources' features (``keep # [k]``: those sources' only, encoded together), with their graph where grad
        is on. The encoder sees the photos as they are; the blend mixes exposure-corrected colours."""
        sources = self.s.sources if keep is None else self.s.sources.subset(keep)
        colours = None
        if self.exposed:
            colours = self.exposure(self.s.sources)
            colours = colours if keep is None else colours.subset(keep)
        return encode_maps(self.s.model, sources, colours=colours)

    def used_sources(self, batch: Batch) -> torch.Tensor | None:
        """The sources ``batch``'s pixels blend (``# [k]`` indices) where some source is unused (under ``--nearest``
        a step's pixels, one tuning view's, blend its nearest visible sources): a step without a reusable pass encodes
        only those, together, as the real-time renderer encodes a frame's nearest sources (the encoder's batch
        normalisation keeps no running statistics: its maps depend a little on the photos encoded together).
        ``None``: every source."""
        if batch.visible is None or batch.weights is not None:
            return None
        used = batch.visible.any(0)  # [K]
        return None if bool(used.all()) or not bool(used.any()) else used.nonzero()[:, 0]

    def scoring_features(self):
        """The current state's features for a score (no graph). Encoded with their graph when the next step can
        reuse them (:attr:`pending`): a score between steps costs no encoder pass of its own."""
        if self.frozen is not None:
            return self.frozen
        if not self.reuse:
            return self.features()
        if self.pending is None:
            start = self.read()
            with torch.enable_grad():
                self.pending = self.features()
            self.pending_cost = self.read() - start
        return OmniReconFeatures(self.pending.sources, self.pending.maps.detach(), self.pending.volume, self.pending.box)

    def view_scoring(self, view: ViewPixels) -> tuple[OmniReconFeatures, ViewPixels]:
        """The current state's features for scoring ``view`` (no graph), and the view with its visibility over them:
        where its pixels blend only some sources (under ``--nearest``: the view's nearest), those sources' features
        only, encoded together, as the real-time renderer encodes a frame's nearest sources and a step the sources
        its pixels blend (:meth:`used_sources`); else :meth:`scoring_features` of every source."""
        keep = None
        if self.frozen is None and not self.reuse and view.visible is not None and view.weights is None:
            used = view.visible.any(0)  # [K]
            keep = used.nonzero()[:, 0] if bool(used.any()) and not bool(used.all()) else None
        if keep is None:
            return self.scoring_features(), view
        with torch.no_grad():
            return self.features(keep), replace(view, visible=view.visible[:, keep])

    def step(self, batch: Batch) -> float:
        """One Adam step on the MSE of ``batch``'s pixels (plus the pull toward the start). Returns the seconds of a
        reused encoder pass (:meth:`scoring_features`), which the budget is charged."""
        reused, self.pending, charge = self.pending, None, self.pending_cost
        self.pending_cost = 0.0
        points = batch.points if self.surface is None else batch.points + self.surface.shift(
            batch.face, batch.bary, batch.points, batch.origins, self.base)
        visible, keep = batch.visible, None
        if self.frozen is None and reused is None:
            keep = self.used_sources(batch)  # encode only the sources the step's pixels blend
            visible = visible if keep is None else visible[:, keep]
        with self.autocast:
            feats = self.frozen if self.frozen is not None else reused if reused is not None else self.features(keep)
            rgb = point_colours(self.s.model, feats, points, batch.origins, visible, batch.weights,
                                self.consensus)  # --blend angle (with --tune residual): the fixed weights
        if self.residual is not None:
            rgb = rgb.float() + self.residual(points)
        loss = (rgb.float() - batch.target).square().mean()
        if self.surface is not None and self.smooth > 0:
            loss = loss + self.smooth * self.surface.smoothness()
        if self.reg > 0 and self.params:
            loss = loss + self.reg * sum((p - p0).square().sum() for p, p0 in zip(self.params, self.start)) / sum(
                p.numel() for p in self.params)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.steps += 1
        if self.retrace is not None and self.every > 0 and self.steps % self.every == 0:
            self.follow()
        return charge if reused is not None else 0.0

    @torch.no_grad()
    def follow(self) -> None:
        """Rasterize the tuning views again on the mesh the offsets move (``--surface-every``): their faces, points
        and occlusion follow the surface; validation and held-out views keep the start's."""
        self.s.train_px = self.retrace(self.surface.moved(self.s.mesh))
        self.base = self.surface.offsets().detach().clone()

    @torch.no_grad()
    def validate(self, val_idx: list[torch.Tensor], val_obj: list[torch.Tensor] | None = None) -> dict[str, float]:
        """PSNR of the current state on the validation pixels (``psnr``; NaN without validation views) and, given
        which of them lie on the objects (``val_obj``), on those (``psnr_masked``)."""
        if not self.s.val_px:
            return {"psnr": float("nan")}
        model = self.s.model
        model.eval()
        views = [(render_pixels(model, *self.view_scoring(v), i, residual=self.residual,
                                surface=self.surface).clamp(0, 1) - v.target[i]).square().mean(-1)
                 for v, i in zip(self.s.val_px, val_idx)]  # per view: [P_v]
        model.train()
        se = torch.cat(views)  # [P]
        out = {"psnr": psnr_of(se)}
        objects = val_obj is not None and bool(torch.cat(val_obj).any())
        if objects:
            out["psnr_masked"] = psnr_of(se[torch.cat(val_obj)])
        # each view's own score on what the scene is scored by (a view without object pixels: its whole image)
        out["per_view"] = [psnr_of(e[o] if self.s.scored_by == "objects" and objects and bool(o.any()) else e)
                           for e, o in zip(views, val_obj if objects else [None] * len(views))]
        return out

    @torch.no_grad()
    def test_scores(self) -> dict:
        self.s.model.eval()
        r = score_held_out(self.s.model, self.view_scoring, self.s.scene, self.s.held_px, self.s.background,
                           self.residual, self.soften, self.surface)
        self.s.model.train()
        return r

    def state(self) -> list[torch.Tensor]:
        return [p.detach().clone() for p in self.params]

    def swap(self, state: list[torch.Tensor]) -> list[torch.Tensor]:
        """Load ``state`` into the tuned parameters; returns the state they had. Drops :attr:`pending` (its graph
        holds the weights this overwrites)."""
        self.pending, self.pending_cost = None, 0.0
        old = self.state()
        with torch.no_grad():
            for p, s in zip(self.params, state):
                p.copy_(s)
        return old


@dataclass
class Tuned:
    """What the tuning loop measured and returns."""

    curve: list[dict]
    validation: list[dict]
    before: dict
    after: dict
    best_val: dict
    """The returned state's validation scores (``psnr``, ``psnr_masked``)."""
    best_gain: float
    """Its validation gain over the start (0: the start is returned)."""
    best_at: tuple[float, int]
    steps: int
    budget_spent: float = 0.0
    """Seconds of optimisation on the budget's clock (steps, and the encoder passes they reused)."""


class Batch(NamedTuple):
    """One step's pixels, from one or several tuning views."""

    points: torch.Tensor
    """``# [n, 3]``"""
    origins: torch.Tensor
    """Camera centre of each pixel's view. ``# [n, 3]``"""
    visible: torch.Tensor | None
    """Sources each point may blend (``None``: no test). ``# [n, K]`` bool"""
    target: torch.Tensor
    """``# [n, 3]``"""
    weights: torch.Tensor | None = None
    """With ``--blend angle``: each point's fixed blend weights (``ViewPixels.weights``). ``# [n, K]``"""
    face: torch.Tensor | None = None
    """With ``--tune surface``: each point's mesh face, -1 off the mesh (``ViewPixels.face``). ``# [n]``"""
    bary: torch.Tensor | None = None
    """With ``--tune surface``: each point's barycentrics on its face. ``# [n, 3]``"""


def batch_of(view: ViewPixels, idx: torch.Tensor) -> Batch:
    """``view``'s pixels at ``idx`` as a :class:`Batch`."""
    return Batch(view.points[idx], view.origin.expand(len(idx), 3), visible_at(view, idx), view.target[idx],
                 *(None if x is None else x[idx] for x in (view.weights, view.face, view.bary)))


class PixelSampler:
    """Each step's pixels: ``--rays`` shaded pixels (on the mesh and, with ``--fill far``, on the fill's layer: both
    are scored; a ``--objects`` share of them on the mesh inside the object masks) of one tuning view drawn by its
    shaded pixel count (``--step-views 1``) or spread over every tuning view in proportion to it (``0``). ``cfg``: the
    run's ``FinetuneConfig`` (``rays``, ``objects``, ``step_views``)."""

    def __init__(self, cfg, s: Setup, g: torch.Generator):
        self.cfg, self.s, self.g = cfg, s, g
        self.sync()

    def sync(self) -> None:
        """Take the setup's tuning views (again, after ``Tuner.follow`` rasterized them on the moved surface)."""
        s = self.s
        self.views = s.train_px
        self.counts = torch.tensor([len(v.points) for v in s.train_px], dtype=torch.float64)  # shaded pixels
        masks = s.scene.masks
        self.inside = [masks[v.index].reshape(-1).bool()[v.pixels[:v.covered]].nonzero()[:, 0] if masks is not None
                       else v.pixels[:0] for v in s.train_px]  # mesh pixels on the objects, per tuning view

    def pick(self, k: int, n: int) -> torch.Tensor:
        """``n`` pixel rows of tuning view ``k`` (the ``--objects`` share inside its masks)."""
        view, inside = self.views[k], self.inside[k]
        n = min(n, len(view.points))
        idx = torch.randint(len(view.points), (n,), generator=self.g)
        if self.cfg.objects > 0 and len(inside):
            m = int(round(self.cfg.objects * n))
            idx[:m] = inside[torch.randint(len(inside), (m,), generator=self.g)]
        return idx

    def views_and_rows(self) -> list[tuple[int, torch.Tensor]]:
        """This step's ``(tuning view, pixel rows)`` pairs."""
        if self.cfg.step_views == 1:
            k = int(torch.multinomial(self.counts, 1, generator=self.g))
            return [(k, self.pick(k, self.cfg.rays))]
        per = torch.bincount(torch.multinomial(self.counts, self.cfg.rays, replacement=True, generator=self.g),
                             minlength=len(self.views))  # [T] pixels per view, by shaded pixel count
        return [(k, self.pick(k, int(n))) for k, n in enumerate(per.tolist()) if n > 0]

    def __call__(self) -> Batch:
        if self.views is not self.s.train_px:
            self.sync()
        parts = [batch_of(self.views[k], idx) for k, idx in self.views_and_rows()]
        if len(parts) == 1:
            return parts[0]
        return Batch(*(None if getattr(parts[0], f) is None else torch.cat([getattr(b, f) for b in parts])
                       for f in Batch._fields))


