"""``omnirecon finetune``: seconds-scale per-scene tuning of the mesh path (``shared/docs/omnirecon.md`` §7).

The mesh is fixed (``--mesh`` or extracted from the model at the source views); every training view
of the scene is rasterized once, giving one surface point per covered pixel. Each step samples
``--rays`` of those pixels, encodes the source views with the 2-D encoder (the feature volume and
the geometry branch are not used by the mesh path and are not computed), colours the points with
the appearance branch (``OmniRecon.shade``) and takes an Adam step on the MSE to the training
images. Only the 2-D encoder and the appearance branch change.

The budget is ``--seconds`` of optimisation (``--clock wall``: wall time; ``cpu``: this process's
CPU time, which other jobs on the machine do not shrink). Evaluations do not count against it: at
each of ``--eval-at`` (seconds of optimisation) the held-out views are rendered through the mesh
(pixels the mesh misses get the scene's background colour: the generator's for procedural
scenes, else the protocol's white or black); with masks, ``psnr_masked`` scores the object pixels only, and ``psnr_covered`` the pixels the mesh covers
(inside the masks): appearance without the mesh's missing parts and their PSNR goes into the curve.

Outputs in ``--out``: ``curve.json`` (every evaluation: seconds, steps, PSNR per view and mean),
``curve.png`` (PSNR against seconds), ``before_after.png`` (GT | before | after for the first
held-out view) and, with ``--save``, the tuned checkpoint.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from omnirecon import metrics
from omnirecon.data import detect_format
from omnirecon.data.io import atomic_path, write_image, write_json
from omnirecon.engine.checkpoint import load_checkpoint, save_checkpoint
from omnirecon.engine.machine import ThreadsConfig, set_threads
from omnirecon.engine.protocols import protocol_for, targets_and_pool
from omnirecon.engine.scenes import load_at_resolution
from omnirecon.engine.views import check_views, default_views
from omnirecon.errors import InputError
from omnirecon.mesh.build import MeshOptions, mesh_from_model
from omnirecon.mesh.files import read_mesh
from omnirecon.models.omnirecon import OmniReconFeatures
from omnirecon.preflight import check_resolution
from omnirecon.provenance import provenance
from omnirecon.rays import Sources
from omnirecon.render.raster import MeshRasterizer

EVAL_AT = (0.0, 10.0, 30.0, 60.0, 180.0, 300.0)
"""Default evaluation points (seconds of optimisation; 0 = before tuning)."""


@dataclass
class FinetuneConfig(ThreadsConfig):
    """Tune Omni-Recon's 2-D encoder and appearance branch on one scene's training views through its
    mesh, within a time budget; writes a PSNR-vs-time curve on the held-out views."""

    ckpt: Path
    """Omni-Recon checkpoint folder (written by `omnirecon train`)."""
    scene: Path
    """Scene folder (any supported format)."""
    seconds: float = 60.0
    """Optimisation budget (see --clock); evaluations are not counted."""
    eval_at: tuple[float, ...] = EVAL_AT
    """Seconds of optimisation at which the held-out views are scored (those beyond --seconds are dropped;
    --seconds itself is always scored)."""
    clock: Literal["wall", "cpu"] = "wall"
    """Budget clock: wall time, or this process's CPU time (fair when other jobs share the machine)."""
    views: tuple[int, ...] | None = None
    """Source views (default: DTU's 23 24 33, else --num-views evenly spaced train views)."""
    num_views: int = 3
    """Source views K when --views is not given."""
    mesh: Path | None = None
    """Mesh file in the input scene's frame (default: `omnirecon mesh`'s mesh from the model at the sources)."""
    resolution: int | None = None
    """Long side of the images in pixels (default: the scene's eval protocol, 128)."""
    rays: int = 2048
    """Surface pixels per step."""
    lr: float = 5e-4
    """Adam learning rate."""
    max_held_out: int = 4
    """Held-out views scored at each evaluation (evenly spaced over the protocol's targets)."""
    out: Path | None = None
    """Output folder (default: outputs/finetune/<scene>)."""
    save: bool = False
    """Also write the tuned checkpoint to <out>/checkpoint."""
    seed: int = 0
    """Seed of the pixel sampling."""
# ---------------------------------------------------------------------- pieces
@dataclass
class ViewPixels:
    """The mesh-covered pixels of one view."""

    index: int
    """Scene view index."""
    origin: torch.Tensor
    """Camera centre. ``# [3]``"""
    points: torch.Tensor
    """Surface point per covered pixel. ``# [P, 3]``"""
    pixels: torch.Tensor
    """Flat pixel indices. ``# [P]``"""
    target: torch.Tensor
    """Ground-truth colour of those pixels. ``# [P, 3]``"""


def rasterize_views(mesh, scene, indices) -> list[ViewPixels]:
    """Rasterize ``mesh`` (scene frame) at each of ``indices`` once."""

    out = []
    with MeshRasterizer.from_trimesh(mesh, cull_back_faces=False) as rast:
        for i in indices:
            cam = scene.cameras[i]
            surf = rast.surface(cam)
            img = scene.images[i].reshape(-1, 3)
            out.append(ViewPixels(i, cam.centers[0].float(), surf.points.float(), surf.pixels,
                                  img[surf.pixels].float()))
    return out


def encode_maps(model, sources):
    """The mesh path's features: the 2-D encoder only (no feature volume). Differentiable."""

    maps, _ = model.encoder(sources.images.permute(0, 3, 1, 2))
    return OmniReconFeatures(sources, maps, maps.new_zeros(0), maps.new_zeros(2, 3))


def render_pixels(model, features, view: ViewPixels, chunk: int = 16384) -> torch.Tensor:
    """Colours of ``view``'s covered pixels through the appearance branch. ``# [P, 3]``"""
    out = []
    for s in range(0, len(view.points), chunk):
        pts = view.points[s:s + chunk]
        out.append(model.shade(features, pts, view.origin.expand_as(pts))["rgb"])
    return torch.cat(out) if out else view.target.new_zeros(0, 3)


def full_image(scene, view: ViewPixels, rgb: torch.Tensor, background=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """The whole image: ``rgb`` at the covered pixels, ``background`` (RGB) elsewhere. ``# [H, W, 3]``"""
    img = torch.tensor(background, dtype=torch.float32).expand(scene.height * scene.width, 3).clone()
    img[view.pixels] = rgb.detach().float().clamp(0, 1)
    return img.reshape(scene.height, scene.width, 3)


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


# ---------------------------------------------------------------------- the run
def run_finetune(cfg: FinetuneConfig) -> dict:
    """Run ``omnirecon finetune``; returns ``{"out", "curve", ...}`` as written to ``curve.json``."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    if not cfg.seconds > 0:
        raise InputError(f"--seconds must be positive, got {cfg.seconds}", None, "use e.g. 60")
    if cfg.rays < 1 or not cfg.lr > 0:
        raise InputError("--rays must be >= 1 and --lr positive", None, "use e.g. --rays 2048 --lr 5e-4")
    check_resolution(cfg.resolution)
    set_threads(cfg.threads)
    model, meta = load_checkpoint(cfg.ckpt)
    if not model.capabilities.appearance:
        raise InputError(f"finetune needs an Omni-Recon checkpoint, got preset {meta['preset']}", cfg.ckpt,
                         "pass checkpoints/omnirecon-tiny or another omnirecon-* checkpoint")
    fmt = detect_format(cfg.scene)
    proto = protocol_for(Path(cfg.scene), fmt)
    scene = load_at_resolution(cfg.scene, cfg.resolution or proto.long_side, proto.background, fmt)
    views = check_views(cfg.views, len(scene), cfg.scene) if cfg.views else default_views(scene, cfg.num_views)
    targets, pool = targets_and_pool(proto, scene)
    if len(targets) > cfg.max_held_out:
        targets = [targets[i] for i in np.unique(np.linspace(0, len(targets) - 1, cfg.max_held_out).round().astype(int))]
    train_views = [i for i in pool if i not in set(targets)]
    out = Path(cfg.out or Path("outputs/finetune") / Path(cfg.scene).name)
    sources = Sources.from_scene(scene, views)
    background = scene.background if scene.background is not None else (
        (0.0,) * 3 if proto.background == "black" else (1.0,) * 3)

    # the fixed mesh, rasterized once per view
    if cfg.mesh is not None:
        mesh = read_mesh(cfg.mesh, scene.to_input)
    else:
        mesh = mesh_from_model(model, scene, views, MeshOptions()).mesh
    if len(mesh.faces) == 0:
        raise InputError("the mesh is empty", cfg.mesh or cfg.ckpt, "check the mesh (or the model's depth)")
    train_px = [v for v in rasterize_views(mesh, scene, train_views) if len(v.points)]
    held_px = rasterize_views(mesh, scene, targets)
    if not train_px:
        raise InputError("the mesh covers no pixel of the training views", cfg.scene, "check the mesh and the poses")
    counts = torch.tensor([len(v.points) for v in train_px], dtype=torch.float64)

    params = list(model.encoder.parameters()) + list(model.appearance.parameters())
    for p in model.parameters():
        p.requires_grad_(False)
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=cfg.lr)
    g = torch.Generator().manual_seed(cfg.seed)
    model.train()

    def evaluate_now() -> dict:
        model.eval()
        with torch.no_grad():
            feats = encode_maps(model, sources)
            renders = [full_image(scene, v, render_pixels(model, feats, v), background) for v in held_px]
        model.train()
        scores = [metrics.psnr(r, scene.images[v.index].float()) for r, v in zip(renders, held_px)]
        out = {"psnr": float(np.mean(scores)), "per_view": scores, "renders": renders}
        if scene.masks is not None:  # the objects only (a mesh cleaned with the masks has no background)
            out["psnr_masked"] = float(np.mean([metrics.psnr(r, scene.images[v.index].float(), scene.masks[v.index])
                                                for r, v in zip(renders, held_px)]))
        covered = []  # appearance alone: the pixels the mesh covers (inside the masks when there are masks)
        for r, v in zip(renders, held_px):
            m = torch.zeros(scene.height * scene.width, dtype=torch.bool)
            m[v.pixels] = True
            m = m.reshape(scene.height, scene.width)
            if scene.masks is not None:
                m &= scene.masks[v.index].bool()
            if m.any():
                covered.append(metrics.psnr(r, scene.images[v.index].float(), m))
        if covered:
            out["psnr_covered"] = float(np.mean(covered))
        return out

    eval_at = sorted({float(t) for t in cfg.eval_at if 0 <= t < cfg.seconds} | {0.0, float(cfg.seconds)})
    curve, before, step = [], None, 0
    clock = Clock(cfg.clock)
    columns = (TextColumn("finetune {task.fields[psnr]}"), BarColumn(), TextColumn("{task.completed:.0f}/{task.total:.0f} s"),
               TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn())
    with Progress(*columns) as bar:
        task = bar.add_task("finetune", total=cfg.seconds, psnr="")
        for t_eval in eval_at:
            clock.start()
            while clock.now() < t_eval:
                view = train_px[int(torch.multinomial(counts, 1, generator=g))]
                idx = torch.randint(len(view.points), (min(cfg.rays, len(view.points)),), generator=g)
                pts = view.points[idx]
                feats = encode_maps(model, sources)
                rgb = model.shade(feats, pts, view.origin.expand_as(pts))["rgb"]
                loss = (rgb - view.target[idx]).square().mean()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                step += 1
                bar.update(task, completed=min(clock.now(), cfg.seconds))
            clock.stop()
            r = evaluate_now()
            before = before or r
            curve.append({"seconds": t_eval, "steps": step, "psnr": r["psnr"], "per_view": r["per_view"],
                          **{k: r[k] for k in ("psnr_masked", "psnr_covered") if k in r}})
            bar.update(task, completed=min(t_eval, cfg.seconds), psnr=f"{r['psnr']:.2f} dB")
    after = r

    # outputs
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    ax.plot([c["seconds"] for c in curve], [c["psnr"] for c in curve], "o-")
    ax.set_xlabel(f"seconds of fine-tuning ({cfg.clock} clock)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title(f"{Path(cfg.scene).name}: mesh path, {len(held_px)} held-out views", fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "curve.png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    gt = scene.images[held_px[0].index].float()
    white = torch.ones(gt.shape[0], 2, 3)
    write_image(out / "before_after.png", torch.cat([gt, white, before["renders"][0], white, after["renders"][0]], 1).numpy())
    result = {"scene": str(cfg.scene), "checkpoint": str(cfg.ckpt), "preset": meta["preset"], "sources": views,
              "held_out": targets, "train_views": len(train_px), "faces": len(mesh.faces), "clock": cfg.clock,
              "budget_s": cfg.seconds, "rays": cfg.rays, "lr": cfg.lr, "tuned": ["encoder", "appearance"],
              "tuned_parameters": sum(p.numel() for p in params), "resolution": [scene.width, scene.height],
              "curve": curve, "gain_db": curve[-1]["psnr"] - curve[0]["psnr"],
              "provenance": provenance(seed=cfg.seed), "out": str(out)}
    write_json(out / "curve.json", result)
    if cfg.save:
        save_checkpoint(out / "checkpoint", model, meta["preset"], step=step,
                        extra={"finetuned_on": str(cfg.scene), "seconds": cfg.seconds})
    return result
