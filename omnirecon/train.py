"""``omnirecon train``: train a generalizable model on procedural and real scenes.

One step = one scene, one random target view, ``K`` sources drawn from the target's ``n`` nearest
training views, ``--rays`` random target pixels; the sources are encoded once per step and the loss
is the MSE of the main colour plus the auxiliary one (GPNR's blended source colours, IBRNet's and
Omni-Recon's coarse pass), over the rays the model marks ``valid``, plus ``--depth-weight`` x the L1
error of the rendered z-depth (both passes) on rays whose ground-truth depth is known (Omni-Recon).

Exact resume: every random choice of step ``s`` on rank ``r`` (scene, target, sources, pixels,
IBRNet's stratified samples) comes from generators seeded by ``(seed, s, r)`` (the scene by
``(seed, s // switch_every, r)``), so a checkpoint needs only weights, optimizer state and the step.

Multi-process: run under ``torchrun --standalone --nproc_per_node=N -m omnirecon.cli train ...``;
each rank draws its own scenes and rays, gradients are averaged by DDP (gloo on CPU, nccl on CUDA)
and rank 0 writes checkpoints, logs and pictures.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import math
import os
import shutil
import sys
import time
import typing
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor, nn

from omnirecon.errors import InputError
from omnirecon.outputs import prepare_out
from omnirecon.preflight import check_train_views

# Per-family defaults: rays per step (docs/gpnr_ibrnet.md Part E), learning rate, Adam betas/eps
# (GPNR: optax.adamw b2 0.98, eps 1e-9; IBRNet: torch Adam), the image encoder's lr multiplier
# (IBRNet: 1e-3 for the U-Net vs 5e-4 for the MLPs) and the depth-loss weight. Omni-Recon
# (docs/omnirecon.md §5, §11.2): the CPU recipe's 256 rays and Adam 5e-4 (the reference: 1024 rays,
# 1e-3 for both groups), L1 depth on both passes (the reference weighs it 1; 0.1 here, see --depth-weight).
FAMILY_DEFAULTS = {
    "gpnr": {"rays": 256, "lr": 5e-4, "betas": (0.9, 0.98), "eps": 1e-9, "encoder_lr_scale": 1.0, "encoder": "patch",
             "depth_weight": 0.0},
    "ibrnet": {"rays": 512, "lr": 5e-4, "betas": (0.9, 0.999), "eps": 1e-8, "encoder_lr_scale": 2.0,
               "encoder": "unet", "depth_weight": 0.0},
    "omnirecon": {"rays": 256, "lr": 5e-4, "betas": (0.9, 0.999), "eps": 1e-8, "encoder_lr_scale": 1.0,
                  "encoder": "encoder", "depth_weight": 0.1},
}
# Fields that may change on --resume without breaking the run's arithmetic.
OPERATIONAL = {"steps", "stop_at", "time_budget", "cpu_budget", "resume", "threads", "device", "val_every", "val_scenes",
               "val_views", "ckpt_every", "keep", "log_every", "out", "cache", "scenes_in_memory", "progress"}


@dataclass
class TrainConfig:
    """Train a generalizable renderer (GPNR, IBRNet or Omni-Recon) on procedural and/or real scenes.

    Writes a run folder: checkpoints/step_XXXXXXX (last --keep), checkpoints/latest (link to the
    newest), checkpoints/final, metrics.jsonl, config.json, val/step_XXXXXXX.png (GT | render |
    error) and TensorBoard events when tensorboard is installed. Scenes are moved so that their content
    fits the unit sphere (GPNR's Fourier encodings and IBRNet's sampling depend on the scene scale).
    Multi-process: ``torchrun --standalone --nproc_per_node=2 -m omnirecon.cli train ...``.
    """

    model: str = "gpnr-tiny"
    """Model preset: gpnr-tiny, gpnr-paper, ibrnet-tiny, ibrnet-paper, omnirecon-tiny or omnirecon-paper."""
    model_overrides: tuple[str, ...] = ()
    """Model config changes: key=value items (values parsed as JSON, e.g. visual_transformer=false,
    layers=[1,1,1], ray_param=lightslab) or one JSON object."""
    data: tuple[str, ...] = ("synth:object",)
    """Training sources: synth:RIG (RIG = object, frontal, forward; synth:RIG:N for N scenes,
    synth:RIG:seeds=A,B for named seeds), a scene folder (any format) or a folder of scene folders."""
    data_weights: tuple[float, ...] | None = None
    """Mixing weight of each --data source (None: equal)."""
    synth_scenes: int = 32
    """Procedural scenes per synth:RIG source without a count."""
    synth_views: int = 40
    """Views per procedural scene."""
    cache: Path = Path("outputs/cache/synth")
    """Where procedural scenes are generated (sub-folder <rig>_<resolution>)."""
    max_views: int | None = None
    """Load at most this many views of each real scene (evenly spaced)."""
    resolution: int = 64
    """Training image size: procedural scenes are generated at it, real scenes downscaled to this long side."""
    steps: int = 1000
    """Optimisation steps (the learning-rate schedule spans them)."""
    rays: int | None = None
    """Target rays per step and process (None: gpnr 256, ibrnet 512, omnirecon 256)."""
    lr: float | None = None
    """Peak learning rate (None: 5e-4)."""
    encoder_lr_scale: float | None = None
    """Learning-rate multiplier of the image encoder (None: ibrnet 2, i.e. 1e-3 for the U-Net; gpnr 1)."""
    warmup: int = 100
    """Linear warm-up steps from 0 to the peak learning rate."""
    schedule: Literal["cosine", "linear", "constant"] = "cosine"
    """Decay after warm-up, down to --min-lr-ratio x the peak at the last step."""
    min_lr_ratio: float = 0.05
    """Final learning rate as a fraction of the peak."""
    weight_decay: float = 0.0
    """AdamW decoupled weight decay (GPNR's reference: 0)."""
    clip: float = 1.0
    """Gradient-norm clipping threshold (0 disables)."""
    aux_weight: float = 1.0
    """Weight of the auxiliary colour loss (GPNR rgb_aux, IBRNet and Omni-Recon coarse pass)."""
    depth_weight: float | None = None
    """Weight of the L1 z-depth loss (both passes) on rays with known ground-truth depth in [near, far]
    (procedural scenes have depths; None: omnirecon 0.1, gpnr/ibrnet 0)."""
    num_views: int | None = None
    """Source views K per step (None: the model's num_views); validation always uses it."""
    num_views_range: tuple[int, int] | None = None
    """Draw K uniformly from ``[lo, hi]`` at every step instead (as IBRNet's reference trains), so a model
    evaluated with K = 3 and K = 10 has seen both; the draw is seeded by the step, so resume stays exact."""
    pool: int | None = None
    """Draw the K sources from the target's n nearest training views (None: 2K); angle around the
    centre for object rigs, camera distance for forward-facing ones."""
    foreground: float = 0.5
    """Fraction of the rays drawn on the foreground mask, for scenes that have masks (procedural ones)."""
    switch_every: int = 10
    """Steps spent on one scene before drawing the next."""
    scenes_in_memory: int = 8
    """Loaded scenes kept in memory (least recently used are dropped)."""
    log_every: int = 10
    """Steps between metrics.jsonl lines (and progress updates)."""
    val_every: int = 250
    """Steps between validations, plus one at the end (0: never)."""
    val_scenes: tuple[str, ...] | None = None
    """Held-out validation scenes: synth:RIG[:N] (first N evaluation seeds) and/or scene folders
    (None: synth:RIG:2 for the first procedural rig of --data)."""
    val_views: int = 1
    """Views rendered per validation scene (its first test views)."""
    ckpt_every: int = 250
    """Steps between checkpoints (0: only at the end)."""
    keep: int = 2
    """Periodic checkpoints kept (plus checkpoints/final)."""
    out: Path | None = None
    """Run folder (None: outputs/train/<model>)."""
    resume: bool = False
    """Continue exactly from the latest checkpoint in --out."""
    stop_at: int | None = None
    """Stop (and checkpoint) after this step without finishing the schedule; continue with --resume."""
    seed: int = 0
    """Seed of the weights, the procedural training scenes and every per-step random draw."""
    device: str = "auto"
    """cpu, cuda, cuda:N or auto (cuda when available)."""
    amp: Literal["none", "bf16", "fp16"] = "none"
    """Mixed precision autocast (CUDA only)."""
    time_budget: float | None = None
    """Seconds of training (summed over resumed runs) after which to checkpoint and stop."""
    cpu_budget: float | None = None
    """CPU seconds of this process (all its threads, summed over resumed runs) after which to checkpoint and
    stop: a budget that other jobs on the machine do not shrink (2 cores x 20 min = 2400)."""
    threads: int | None = None
    """Torch CPU threads per process (None: torch's choice; torchrun sets 1)."""
    progress: bool = True
    """Show the progress bar."""

    def main(self) -> None:
        prepare_out(self.out or Path("outputs/train") / self.model, recursive=True)  # before any work
        env = DistEnv.from_env()
        trainer = Trainer(self, env)
        try:
            trainer.run()
        finally:
            trainer.close()
        if env.world > 1:  # clean exit recipe (docs/deps.md §7): avoids a teardown abort in gloo
            import torch.distributed as dist

            dist.barrier()
            dist.destroy_process_group()
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(0)


# ---------------------------------------------------------------------- helpers
@dataclass
class DistEnv:
    """Process group membership from torchrun's environment (world 1 without torchrun)."""

    world: int = 1
    rank: int = 0
    local_rank: int = 0

    @staticmethod
    def from_env() -> DistEnv:
        return DistEnv(int(os.environ.get("WORLD_SIZE", 1)), int(os.environ.get("RANK", 0)),
                       int(os.environ.get("LOCAL_RANK", 0)))

    @property
    def main(self) -> bool:
        return self.rank == 0


def step_seed(*key: int) -> int:
    """A 63-bit seed from integers (``(seed, step, rank)``), independent across keys."""
    return int(np.random.SeedSequence([k & 0xFFFFFFFF for k in key]).generate_state(2, np.uint64)[0] >> np.uint64(1))


def lr_factor(step: int, steps: int, warmup: int, schedule: str, min_ratio: float) -> float:
    """Learning-rate multiplier of 1-based ``step``: linear warm-up, then decay to ``min_ratio`` at ``steps``."""
    if warmup > 0 and step <= warmup:
        return step / warmup
    if schedule == "constant" or steps <= warmup:
        return 1.0
    p = min(1.0, (step - warmup) / (steps - warmup))
    if schedule == "linear":
        return 1.0 - (1.0 - min_ratio) * p
    return min_ratio + (1.0 - min_ratio) * 0.5 * (1.0 + math.cos(math.pi * p))


def parse_overrides(items, cfg_cls) -> dict:
    """``key=value`` items or JSON objects -> a dict checked against the fields of ``cfg_cls``."""
    out: dict = {}
    for item in items:
        s = item.strip()
        if s.startswith("{"):
            try:
                obj = json.loads(s)
            except json.JSONDecodeError as e:
                raise InputError(f"--model-overrides: invalid JSON ({e})", None, 'write e.g. \'{"dim": 32}\'') from e
            if not isinstance(obj, dict):
                raise InputError("--model-overrides: JSON must be an object", None, 'write e.g. \'{"dim": 32}\'')
            out.update(obj)
        elif "=" in s:
            key, value = (p.strip() for p in s.split("=", 1))
            out[key] = _json_value(value)
        else:
            raise InputError(f"--model-overrides: {item!r} is not key=value", None, "write e.g. dim=32")
    hints = typing.get_type_hints(cfg_cls)
    defaults = {f.name: f.default for f in dataclasses.fields(cfg_cls)}
    for key, value in out.items():
        if key not in defaults:
            raise InputError(f"--model-overrides: unknown option {key!r}", None,
                             "options are: " + ", ".join(sorted(defaults)))
        out[key] = _check_value(key, value, defaults[key], hints[key])
    return out


def _json_value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        if "," in text:
            return [_json_value(t) for t in text.split(",")]
        return text


def _check_value(key: str, value, default, hint):
    bad = InputError(f"--model-overrides: {key}={value!r} has the wrong type (default {default!r})", None,
                     f"give a value like {json.dumps(default if not isinstance(default, tuple) else list(default))}")
    if typing.get_origin(hint) is Literal:
        if value not in typing.get_args(hint):
            raise InputError(f"--model-overrides: {key} must be one of {list(typing.get_args(hint))}, got {value!r}",
                             None, f"pass {key}=<one of those>")
        return value
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad
    elif isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
    elif isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad
        value = float(value)
    elif isinstance(default, tuple):
        if not isinstance(value, list) or len(value) != len(default) or \
                not all(isinstance(v, type(d)) and not isinstance(v, bool) for v, d in zip(value, default)):
            raise bad
        value = tuple(value)
    elif isinstance(default, str) and not isinstance(value, str):
        raise bad
    return value


def masked_mse(pred: Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """Mean squared error over rays weighted by ``weight # [R]`` (0 where no weight, graph kept)."""
    err = (pred.float() - target.float()).square().mean(-1)  # [R]
    return (err * weight).sum() / weight.sum().clamp_min(1.0)


def masked_l1(pred: Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """Mean absolute error over rays ``# [R]`` weighted by ``weight # [R]`` (0 where no weight, graph kept)."""
    return ((pred.float() - target.float()).abs() * weight).sum() / weight.sum().clamp_min(1.0)


def depth_loss(out: dict[str, Tensor], depth: Tensor, valid: Tensor, near: float, far: float) -> Tensor:
    """L1 of the rendered z-depth (fine and coarse passes, where rendered) on valid rays whose
    ground-truth ``depth # [R]`` lies in ``[near, far]`` (0 = unknown)."""
    known = valid * ((depth >= near) & (depth <= far)).float()  # [R]
    loss = masked_l1(out["depth"], depth, known)
    if "depth_coarse" in out and out["depth_coarse"] is not out["depth"]:
        loss = loss + masked_l1(out["depth_coarse"], depth, known)
    return loss


class LossModule(nn.Module):
    """encode + render_rays + loss in one ``forward``, the module DDP wraps."""

    def __init__(self, model: nn.Module, aux_weight: float, depth_weight: float = 0.0):
        super().__init__()
        self.model = model
        self.aux_weight = aux_weight
        self.depth_weight = depth_weight
        self.jitter = "jitter" in inspect.signature(model.render_rays).parameters  # IBRNet: stratified samples

    def forward(self, sources, rays, rgb: Tensor, depth: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """-> loss, main-colour MSE (detached) and the fraction of valid rays."""
        out = self.model.render_rays(self.model.encode(sources), rays, **({"jitter": True} if self.jitter else {}))
        valid = out["valid"].float() if "valid" in out else torch.ones_like(rgb[:, 0])  # [R]
        mse = masked_mse(out["rgb"], rgb, valid)
        loss = mse
        aux = out.get("rgb_aux", out.get("rgb_coarse"))
        if aux is not None and aux is not out["rgb"] and self.aux_weight > 0:
            loss = loss + self.aux_weight * masked_mse(aux, rgb, valid)
        if self.depth_weight > 0 and depth is not None and "depth" in out:
            loss = loss + self.depth_weight * depth_loss(out, depth, valid, sources.near, sources.far)
        return loss, mse.detach(), valid.mean().detach()


def param_digest(model: nn.Module) -> str:
    """SHA-256 of every parameter's bytes, in state-dict order."""
    h = hashlib.sha256()
    for k, v in model.state_dict().items():
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def psnr(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-10))


# ---------------------------------------------------------------------- the trainer
class Trainer:
    """Holds the run's state; ``run()`` trains from scratch or the latest checkpoint."""

    def __init__(self, cfg: TrainConfig, env: DistEnv):
        from omnirecon.data.bank import SceneBank, parse_sources
        from omnirecon.models.registry import _families, family_of

        from rich.console import Console

        self.cfg, self.env = cfg, env
        self.threads_before = torch.get_num_threads()
        self.console = Console(stderr=True)
        self.writer = self.metrics = self.pg = None
        self.notes: list[str] = []
        family = family_of(cfg.model)
        if family not in FAMILY_DEFAULTS:
            raise InputError(f"model {cfg.model!r} has no trainable parameters (a non-learned floor)", None,
                             "train gpnr-tiny, gpnr-paper, ibrnet-tiny, ibrnet-paper, omnirecon-tiny or "
                             "omnirecon-paper")
        self.family, self.fam = family, FAMILY_DEFAULTS[family]
        _, cfg_cls, presets = _families()[family]
        self.overrides = parse_overrides(cfg.model_overrides, cfg_cls)
        model_cfg = dataclasses.replace(presets[cfg.model], **self.overrides)
        self.K = model_cfg.num_views if cfg.num_views is None else cfg.num_views
        self.pool = 2 * self.K if cfg.pool is None else cfg.pool
        self.rays = self.fam["rays"] if cfg.rays is None else cfg.rays
        self.lr = self.fam["lr"] if cfg.lr is None else cfg.lr
        self.depth_weight = self.fam["depth_weight"] if cfg.depth_weight is None else cfg.depth_weight
        self.out = Path("outputs/train") / cfg.model if cfg.out is None else cfg.out
        self.check()
        self.device = self.pick_device()

        common = dict(seed=cfg.seed, synth_scenes=cfg.synth_scenes, cache=cfg.cache, resolution=cfg.resolution,
                      synth_views=cfg.synth_views, notes=self.notes)
        self.train_sources = parse_sources(cfg.data, "train", **common)
        self.bank = SceneBank(self.train_sources, list(cfg.data_weights) if cfg.data_weights else None,
                              cfg.resolution, cfg.scenes_in_memory, cfg.max_views)
        val_specs = cfg.val_scenes
        if val_specs is None:
            rig = next((d.split(":")[1] for d in cfg.data if d.startswith("synth:") and d.count(":") >= 1), None)
            val_specs = (f"synth:{rig}:2",) if rig else ()
            if not rig:
                self.notes.append("no --val-scenes: validation skipped (pass held-out scene folders to enable it)")
        val_refs = [r for src in parse_sources(val_specs, "val", **common) for r in src]
        self.val_bank = SceneBank([val_refs], None, cfg.resolution, max(1, len(val_refs)), cfg.max_views) \
            if val_refs else None
        self.val_refs = val_refs

    # ------------------------------------------------------------------ set-up
    def check(self) -> None:
        c = self.cfg

        def need(ok: bool, what: str, fix: str) -> None:
            if not ok:
                raise InputError(what, None, fix)

        need(c.steps >= 1, f"--steps must be at least 1, got {c.steps}", "use e.g. --steps 1000")
        need(self.rays >= 1, f"--rays must be at least 1, got {self.rays}", "use e.g. --rays 256")
        need(c.resolution >= 8, f"--resolution must be at least 8, got {c.resolution}", "use e.g. --resolution 64")
        need(self.lr > 0, f"--lr must be positive, got {self.lr}", "use e.g. --lr 5e-4")
        need(c.encoder_lr_scale is None or c.encoder_lr_scale >= 0, "--encoder-lr-scale must be >= 0", "use e.g. 1")
        need(c.warmup >= 0, f"--warmup must be >= 0, got {c.warmup}", "use e.g. --warmup 100")
        need(0 <= c.min_lr_ratio <= 1, f"--min-lr-ratio must be in [0, 1], got {c.min_lr_ratio}", "use e.g. 0.05")
        need(c.weight_decay >= 0, "--weight-decay must be >= 0", "use 0 (the reference) or e.g. 0.01")
        need(c.clip >= 0, "--clip must be >= 0 (0 disables)", "use e.g. --clip 1")
        need(c.aux_weight >= 0, "--aux-weight must be >= 0", "use e.g. 1")
        need(self.depth_weight >= 0, "--depth-weight must be >= 0", "use e.g. 0.1 (0 disables)")
        need(self.K >= 1, f"--num-views must be at least 1, got {self.K}", "use e.g. --num-views 5")
        need(self.pool >= self.K, f"--pool ({self.pool}) must be at least --num-views ({self.K})",
             "pass --pool >= --num-views")
        if c.num_views_range is not None:
            lo, hi = c.num_views_range
            need(1 <= lo <= hi, f"--num-views-range needs 1 <= lo <= hi, got {lo} {hi}",
                 "use e.g. --num-views-range 3 10")
            need(c.pool is None or c.pool >= hi, f"--pool ({c.pool}) must be at least the range's top ({hi})",
                 "pass --pool >= hi or leave it out (2K)")
        need(0 <= c.foreground <= 1, f"--foreground must be in [0, 1], got {c.foreground}", "use e.g. 0.5")
        need(c.switch_every >= 1, "--switch-every must be at least 1", "use e.g. --switch-every 10")
        need(c.scenes_in_memory >= 1, "--scenes-in-memory must be at least 1", "use e.g. 8")
        need(c.synth_scenes >= 1 and c.synth_views >= 2, "--synth-scenes must be >= 1 and --synth-views >= 2",
             "use e.g. --synth-scenes 32 --synth-views 40")
        need(c.max_views is None or c.max_views >= 2, "--max-views must be at least 2", "use e.g. --max-views 40")
        need(c.log_every >= 1, "--log-every must be at least 1", "use e.g. --log-every 10")
        need(c.val_every >= 0 and c.ckpt_every >= 0, "--val-every and --ckpt-every must be >= 0", "0 disables them")
        need(c.val_views >= 1, "--val-views must be at least 1", "use e.g. --val-views 1")
        need(c.keep >= 1, "--keep must be at least 1", "use e.g. --keep 2")
        need(len(c.data) >= 1, "--data needs at least one source", "use e.g. --data synth:object")
        need(c.data_weights is None or (len(c.data_weights) == len(c.data) and all(w > 0 for w in c.data_weights)),
             f"--data-weights needs one positive weight per --data source ({len(c.data)})",
             "e.g. --data-weights 0.7 0.3")
        need(c.stop_at is None or c.stop_at >= 1, "--stop-at must be at least 1", "use a step number")
        need(c.time_budget is None or c.time_budget > 0, "--time-budget must be positive (seconds)", "e.g. 2700")
        need(c.cpu_budget is None or c.cpu_budget > 0, "--cpu-budget must be positive (CPU seconds)", "e.g. 2400")
        need(c.threads is None or c.threads >= 1, "--threads must be at least 1", "use e.g. --threads 2")
        if self.out.exists() and not self.out.is_dir():
            raise InputError("run folder path is a file", self.out, "pass a folder for --out")
        from omnirecon.checkpoint_check import resume_folder

        self.resume_from = resume_folder(self.out, self.notes) if c.resume else None
        if not c.resume and (self.out / "checkpoints").is_dir() and any((self.out / "checkpoints").iterdir()):
            raise InputError("run folder already has checkpoints", self.out,
                             "pass --resume to continue it, or choose a new --out")

    def views_at(self, step: int) -> tuple[int, int]:
        """Source views K and pool size of 1-based ``step`` (fixed unless ``num_views_range`` is set)."""
        c = self.cfg
        if c.num_views_range is None:
            return self.K, self.pool
        lo, hi = c.num_views_range
        gen = torch.Generator().manual_seed(step_seed(c.seed, step, self.env.rank, 3))
        K = int(torch.randint(lo, hi + 1, (1,), generator=gen))
        return K, (2 * K if c.pool is None else c.pool)

    def pick_device(self) -> torch.device:
        c = self.cfg
        cuda = torch.cuda.is_available()
        if c.device == "auto":
            dev = torch.device(f"cuda:{self.env.local_rank}" if cuda else "cpu")
        else:
            try:
                dev = torch.device(c.device)
            except RuntimeError as e:
                raise InputError(f"bad --device {c.device!r}", None, "use cpu, cuda, cuda:N or auto") from e
            if dev.type == "cuda" and not cuda:
                raise InputError("--device cuda but CUDA is not available", None, "use --device cpu or auto")
            if dev.type == "cuda" and dev.index is None:
                dev = torch.device(f"cuda:{self.env.local_rank}")
        if c.amp != "none" and dev.type != "cuda":
            raise InputError(f"--amp {c.amp} needs CUDA (training on {dev})", None, "drop --amp on CPU")
        return dev

    def setup(self) -> None:
        from omnirecon.checkpoint import load_optimizer_state, read_meta
        from omnirecon.models.registry import build_model, model_config_dict
        from omnirecon.provenance import provenance

        c, env = self.cfg, self.env
        if c.threads:
            torch.set_num_threads(c.threads)
        if env.world > 1:
            import torch.distributed as dist

            if self.device.type == "cuda":
                torch.cuda.set_device(self.device)
            dist.init_process_group("nccl" if self.device.type == "cuda" else "gloo")
        torch.manual_seed(c.seed)
        self.model = build_model(c.model, self.overrides).to(self.device)
        self.loss_module = LossModule(self.model, c.aux_weight, self.depth_weight)
        self.ddp = self.loss_module
        if env.world > 1:
            from torch.nn.parallel import DistributedDataParallel

            self.ddp = DistributedDataParallel(self.loss_module,
                                               device_ids=[self.device.index] if self.device.type == "cuda" else None)
        enc_scale = self.fam["encoder_lr_scale"] if c.encoder_lr_scale is None else c.encoder_lr_scale
        enc, rest = [], []
        for name, p in self.model.named_parameters():
            (enc if name.split(".")[0] == self.fam["encoder"] else rest).append(p)
        groups = [{"params": rest, "base_lr": self.lr}, {"params": enc, "base_lr": self.lr * enc_scale}]
        self.opt = torch.optim.AdamW([g for g in groups if g["params"]], lr=self.lr, betas=self.fam["betas"],
                                     eps=self.fam["eps"], weight_decay=c.weight_decay)
        self.scaler = torch.amp.GradScaler("cuda", enabled=c.amp == "fp16")
        self.step, self.elapsed, self.cpu_used = 0, 0.0, 0.0
        self.prov = provenance(c.seed, world_size=env.world)
        if c.resume:  # from checkpoints/latest, else the newest intact step_* (see check)
            latest = self.resume_from
            meta = read_meta(latest)
            self.check_resume(meta)
            from omnirecon.checkpoint_check import read_weights

            state = read_weights(latest / "model.safetensors", str(self.device))
            self.model.load_state_dict(state)
            load_optimizer_state(latest, self.opt)
            self.step = int(meta["step"])
            self.elapsed = float(meta["extra"].get("elapsed_s", 0.0))
            self.cpu_used = float(meta["extra"].get("cpu_s", 0.0))
            if meta["extra"].get("scaler"):
                self.scaler.load_state_dict(meta["extra"]["scaler"])
        self.model_config = model_config_dict(self.model)
        check_train_views(self.bank, self.train_sources, max(self.cfg.num_views_range or (self.K,)))  # before any file
        if env.main:
            self.open_logs()

    def check_resume(self, meta: dict) -> None:
        saved = meta.get("train_config", {})
        now = self.config_dict()
        diff = [k for k in now if k not in OPERATIONAL | {"num_views_range"} and k in saved and saved[k] != now[k]]
        if meta.get("preset") != self.cfg.model or diff:
            what = ", ".join(f"--{k.replace('_', '-')} {saved[k]} -> {now[k]}" for k in diff) or \
                f"model {meta.get('preset')} -> {self.cfg.model}"
            raise InputError(f"--resume with a different setup ({what})", self.out,
                             "pass the same flags as the original run (see config.json), or a new --out")
        if meta.get("extra", {}).get("world_size", self.env.world) != self.env.world:
            self.notes.append(f"the checkpoint was written by {meta['extra']['world_size']} process(es), this run has "
                              f"{self.env.world}: per-rank random draws differ from an uninterrupted run")
        if saved.get("steps") != now["steps"]:
            self.notes.append(f"--steps changed {saved.get('steps')} -> {now['steps']}: the learning-rate schedule "
                              "changes, so the run is no longer the one a single invocation would give")
        if saved.get("num_views_range") != now["num_views_range"]:
            self.notes.append(f"--num-views-range changed {saved.get('num_views_range')} -> {now['num_views_range']}: "
                              "the run continues on a different view-count distribution")

    def config_dict(self) -> dict:
        d = json.loads(json.dumps(dataclasses.asdict(self.cfg), default=str))
        d["out"] = str(self.out)
        return d

    def open_logs(self) -> None:
        self.out.mkdir(parents=True, exist_ok=True)
        metrics = self.out / "metrics.jsonl"
        if self.cfg.resume and metrics.is_file():  # drop lines a crashed run wrote after the checkpoint
            keep = [ln for ln in metrics.read_text().splitlines() if ln.strip() and json.loads(ln)["step"] <= self.step]
            metrics.write_text("".join(ln + "\n" for ln in keep))
        elif metrics.exists():
            metrics.unlink()
        self.metrics = open(metrics, "a")
        from omnirecon.data.io import write_json

        write_json(self.out / "config.json", {
            "train": self.config_dict(), "model_config": self.model_config, "resolved": {
                "num_views": self.K, "pool": self.pool, "rays": self.rays, "lr": self.lr,
                "depth_weight": self.depth_weight, "family": self.family,
                "world_size": self.env.world, "device": str(self.device), "train_scenes": len(self.bank),
                "val_scenes": [r.name for r in self.val_refs]},
            "provenance": self.prov})
        try:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(self.out / "tb"))
        except ImportError:
            self.notes.append("tensorboard is not installed: no event files (metrics.jsonl has every number)")

    # ------------------------------------------------------------------ the loop
    def run(self) -> None:
        from omnirecon.data.bank import draw_batch

        self.setup()
        c, env = self.cfg, self.env
        for note in self.notes:
            self.say(f"note: {note}")
        last = min(c.steps, c.stop_at or c.steps)
        if self.step >= last or self.over_budget():
            self.say(f"nothing to do: the checkpoint in {self.out} is at step {self.step} after {self.elapsed:.0f} s "
                     "(raise --steps or --time-budget to train on)")
            return
        self.start_progress(last)
        window = torch.zeros(4, dtype=torch.float64)  # loss, mse, steps, step seconds since the last log line
        t0 = time.perf_counter() - self.elapsed
        cpu0 = time.process_time() - self.cpu_used
        while self.step < last:
            s = self.step + 1
            t_step = time.perf_counter()
            gen = torch.Generator().manual_seed(step_seed(c.seed, s, env.rank))
            torch.manual_seed(step_seed(c.seed, s, env.rank, 1))  # model-internal draws (IBRNet jitter)
            ref = self.bank.choose(torch.Generator().manual_seed(step_seed(c.seed, (s - 1) // c.switch_every,
                                                                           env.rank, 2)))
            K, pool = self.views_at(s)
            batch = draw_batch(self.bank.get(ref), K, pool, self.rays, gen, c.foreground).to(self.device)
            loss, mse = self.optimise(s, batch)
            window += torch.tensor([loss, mse, 1.0, time.perf_counter() - t_step], dtype=torch.float64)
            self.step = s
            self.elapsed = time.perf_counter() - t0
            self.cpu_used = time.process_time() - cpu0
            stop = self.agree(self.over_budget())
            end = stop or s == last
            if s % c.log_every == 0 or end:
                loss_sum, mse_sum, n, secs = self.reduce(window)  # sums over ranks
                secs = max(secs / env.world, 1e-9)  # ranks run side by side
                row = {"step": s, "loss": loss_sum / n, "psnr": psnr(mse_sum / n), "lr": self.opt.param_groups[0]["lr"],
                       "rays_per_s": n * self.rays / secs, "steps_per_s": n / env.world / secs,
                       "time": self.elapsed, "cpu_time": self.cpu_used, "scene": ref.name}
                self.log(row)
                window.zero_()
            if c.val_every and s % c.val_every == 0 and not end:
                self.validate(s)
            if c.ckpt_every and s % c.ckpt_every == 0 and not end:
                self.checkpoint(s)
            if stop:
                self.say(f"budget reached at step {s} ({self.elapsed:.0f} s wall, {self.cpu_used:.0f} CPU s)")
                break
        self.finish(self.step)

    def optimise(self, s: int, batch) -> tuple[float, float]:
        """One optimizer step at 1-based step ``s``; returns the loss and main-colour MSE."""
        c = self.cfg
        f = lr_factor(s, c.steps, c.warmup, c.schedule, c.min_lr_ratio)
        for g in self.opt.param_groups:
            g["lr"] = g["base_lr"] * f
        amp = torch.autocast("cuda", dtype=torch.bfloat16 if c.amp == "bf16" else torch.float16) \
            if c.amp != "none" else nullcontext()
        with amp:
            loss, mse, _ = self.ddp(batch.sources, batch.rays, batch.rgb, batch.depth)
        self.opt.zero_grad(set_to_none=True)
        self.scaler.scale(loss).backward()
        if c.clip > 0:
            self.scaler.unscale_(self.opt)
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), c.clip)
        self.scaler.step(self.opt)
        self.scaler.update()
        return float(loss.detach()), float(mse)

    def finish(self, step: int) -> None:
        if self.cfg.val_every:
            self.validate(step)
        self.checkpoint(step, final=True)
        digests = self.gather(param_digest(self.model))
        if self.env.main:
            in_sync = len(set(digests)) == 1
            summary = {"step": step, "time": self.elapsed, "world_size": self.env.world, "params_in_sync": in_sync,
                       "param_sha256": digests}
            from omnirecon.data.io import write_json

            write_json(self.out / "summary.json", summary)
            if not in_sync:
                self.say("[red]error: parameters differ between processes[/red]")
            self.stop_progress()
            self.say(f"run folder: {self.out}\n  checkpoints: {self.out / 'checkpoints'} (latest, final)\n"
                     f"  metrics: {self.out / 'metrics.jsonl'}\n  config: {self.out / 'config.json'}"
                     + (f"\n  validation pictures: {self.out / 'val'}" if self.val_bank is not None else ""))

    def over_budget(self) -> bool:
        c = self.cfg
        return (c.time_budget is not None and self.elapsed >= c.time_budget) or \
            (c.cpu_budget is not None and self.cpu_used >= c.cpu_budget)

    # ------------------------------------------------------------------ distributed helpers
    def agree(self, flag: bool) -> bool:
        """Whether any rank raised ``flag`` (every rank gets the same answer)."""
        if self.env.world == 1 or (self.cfg.time_budget is None and self.cfg.cpu_budget is None):
            return flag
        import torch.distributed as dist

        t = torch.tensor([float(flag)], device=self.device)
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        return bool(t.item() > 0)

    def reduce(self, x: Tensor) -> list[float]:
        """Sum of ``x`` over ranks."""
        if self.env.world > 1:
            import torch.distributed as dist

            x = x.to(self.device, torch.float64 if self.device.type == "cpu" else torch.float32)
            dist.all_reduce(x)
        return [float(v) for v in x.cpu()]

    def gather(self, obj) -> list:
        if self.env.world == 1:
            return [obj]
        import torch.distributed as dist

        out = [None] * self.env.world
        dist.all_gather_object(out, obj)
        return out

    def barrier(self) -> None:
        if self.env.world > 1:
            import torch.distributed as dist

            dist.barrier()

    # ------------------------------------------------------------------ outputs (rank 0)
    def say(self, text: str) -> None:
        """Print on rank 0 (stderr, above the progress bar when it is shown)."""
        if self.env.main:
            self.console.print(text)

    def start_progress(self, last: int) -> None:
        if not (self.env.main and self.cfg.progress):
            return
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
        from rich.progress import TimeRemainingColumn

        self.pg = Progress(TextColumn(f"train {self.cfg.model}"), BarColumn(bar_width=24), MofNCompleteColumn(),
                           TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                           TextColumn("{task.fields[info]}"), console=self.console, transient=False)
        self.pg.start()
        self.task = self.pg.add_task("train", total=last, completed=self.step, info="")

    def stop_progress(self) -> None:
        if self.pg is not None:
            self.pg.stop()
            self.pg = None

    def log(self, row: dict) -> None:
        if not self.env.main:
            return
        self.metrics.write(json.dumps(row) + "\n")
        self.metrics.flush()
        if self.writer is not None:
            for k in ("loss", "psnr", "lr", "rays_per_s"):
                self.writer.add_scalar(f"train/{k}", row[k], row["step"])
        if self.pg is not None:
            self.pg.update(self.task, completed=row["step"],
                           info=f"loss {row['loss']:.4f}  PSNR {row['psnr']:.2f}  {row['rays_per_s']:.0f} rays/s")

    @torch.no_grad()
    def validate(self, step: int) -> None:
        """Render the first test views of each validation scene with their K nearest training views."""
        if self.val_bank is None:
            return
        if self.env.main:
            from omnirecon.data.bank import val_views

            self.model.eval()
            rows, per_scene = [], {}
            t = time.perf_counter()
            for ref in self.val_refs:
                ps = self.val_bank.get(ref)
                errs = []
                for target, srcs in val_views(ps, self.cfg.val_views, self.K):
                    feats = self.model.encode(ps.sources(srcs).to(self.device))
                    out = self.model.render_view(feats, ps.scene.cameras[[target]].to(self.device), chunk=1024)
                    pred = out["rgb"].float().clamp(0, 1).cpu()
                    gt = ps.scene.images[target]
                    errs.append(float((pred - gt).square().mean()))
                    rows.append((gt, pred))
                per_scene[ref.name] = psnr(float(np.mean(errs)))
            self.model.train()
            val_psnr = float(np.mean(list(per_scene.values())))
            row = {"step": step, "val_psnr": val_psnr, "val_psnr_per_scene": per_scene,
                   "val_time": time.perf_counter() - t}
            self.metrics.write(json.dumps(row) + "\n")
            self.metrics.flush()
            if self.writer is not None:
                self.writer.add_scalar("val/psnr", val_psnr, step)
            save_val_picture(self.out / "val" / f"step_{step:07d}.png", rows)
            self.say(f"step {step}: validation PSNR {val_psnr:.2f} dB on {len(per_scene)} scene(s)")
        self.barrier()

    def checkpoint(self, step: int, final: bool = False) -> None:
        if self.env.main:
            from omnirecon.checkpoint import save_checkpoint

            ckdir = self.out / "checkpoints"
            folder = ckdir / f"step_{step:07d}"
            scaler = self.scaler.state_dict() if self.scaler.is_enabled() else None
            extra = {"elapsed_s": self.elapsed, "cpu_s": self.cpu_used, "scaler": scaler, "world_size": self.env.world}
            save_checkpoint(folder, self.model, self.cfg.model, step, self.opt, self.config_dict(), extra, self.prov)
            point_latest(ckdir, folder.name)
            steps = sorted(p for p in ckdir.glob("step_*") if p.is_dir())
            for old in steps[:-self.cfg.keep]:
                shutil.rmtree(old, ignore_errors=True)
            if final:
                tmp = ckdir / ".final.tmp"
                shutil.rmtree(tmp, ignore_errors=True)
                shutil.copytree(folder, tmp)
                shutil.rmtree(ckdir / "final", ignore_errors=True)
                os.replace(tmp, ckdir / "final")
        self.barrier()

    def close(self) -> None:
        torch.set_num_threads(self.threads_before)
        self.stop_progress()
        if self.metrics is not None:
            self.metrics.close()
        if self.writer is not None:
            self.writer.close()


def point_latest(ckdir: Path, name: str) -> None:
    """Make ``ckdir/latest`` a relative link to ``name``, replaced atomically (a copy where links fail)."""
    tmp = ckdir / ".latest.tmp"
    if tmp.is_symlink() or tmp.exists():
        tmp.unlink() if tmp.is_symlink() or tmp.is_file() else shutil.rmtree(tmp)
    try:
        os.symlink(name, tmp, target_is_directory=True)
        if (ckdir / "latest").is_dir() and not (ckdir / "latest").is_symlink():
            shutil.rmtree(ckdir / "latest")
        os.replace(tmp, ckdir / "latest")
    except OSError:
        shutil.copytree(ckdir / name, tmp)
        if (ckdir / "latest").is_symlink():
            (ckdir / "latest").unlink()
        shutil.rmtree(ckdir / "latest", ignore_errors=True)
        os.replace(tmp, ckdir / "latest")


def save_val_picture(path: Path, rows: list[tuple[Tensor, Tensor]], max_err: float = 0.25) -> None:
    """One row per view: ground truth | render | absolute error (mean over RGB, inferno, 0..``max_err``)."""
    from matplotlib import colormaps

    from omnirecon.data.io import write_image

    cmap = colormaps["inferno"]
    lines = []
    for gt, pred in rows:
        err = (pred - gt).abs().mean(-1).numpy() / max_err  # [H, W]
        heat = cmap(np.clip(err, 0, 1))[..., :3].astype(np.float32)
        sep = np.ones((gt.shape[0], 2, 3), np.float32)
        lines.append(np.concatenate([gt.numpy(), sep, pred.numpy(), sep, heat], 1))
    width = max(line.shape[1] for line in lines)
    pic = np.concatenate([np.pad(line, ((0, 2), (0, width - line.shape[1]), (0, 0)), constant_values=1)
                          for line in lines], 0)
    write_image(path, pic)
