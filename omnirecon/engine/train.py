"""``omnirecon train``: train a generalizable model on procedural and real scenes.

One step = one scene, one random target view, ``K`` sources drawn from the target's ``n`` nearest
training views, ``--rays`` random target pixels; the sources are encoded once per step and the loss
is the MSE of the main colour plus the auxiliary one (GPNR's blended source colours, IBRNet's and
Omni-Recon's coarse pass), over the rays the model marks ``valid``, plus ``--depth-weight`` x the L1
error of the rendered z-depth (both passes) on rays whose ground-truth depth is known (Omni-Recon), plus
``--mask-weight`` x the squared error of the accumulated opacity against the object mask (scenes with masks).

Exact resume: every random choice of step ``s`` on rank ``r`` (scene, target, sources, pixels,
IBRNet's stratified samples) comes from generators seeded by ``(seed, s, r)`` (the scene by
``(seed, s // switch_every, r)``), so a checkpoint needs only weights, optimizer state and the step.

Stopping politely: SIGTERM ends the run after the current step with a checkpoint (as a reached budget
does), so ``kill PID`` keeps every finished step and ``--resume`` continues exactly from it.

Multi-process: run under ``torchrun --standalone --nproc_per_node=N -m omnirecon.cli train ...``;
each rank draws its own scenes and rays, gradients are averaged by DDP (gloo on CPU, nccl on CUDA)
and rank 0 writes checkpoints, logs and pictures.

Size: one Trainer class whose methods share the run's state (device, bank, optimiser, logs, distributed
group); its config, losses, checkpoints and process group live in their own modules.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import signal
import threading
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from omnirecon.data.bank import SceneBank, draw_batch, parse_sources, val_views
from omnirecon.data.io import write_json
from omnirecon.engine.checkpoint import (
    checkpoint_weights,
    load_optimizer_state,
    param_digest,
    point_latest,
    read_meta,
    save_checkpoint,
)
from omnirecon.engine.distributed import DistEnv
from omnirecon.engine.losses import LossModule, psnr
from omnirecon.engine.pseudo_depth import StereoPseudoDepth
from omnirecon.engine.report import save_val_picture
from omnirecon.engine.shipped import checkpoint_folder
from omnirecon.engine.train_config import FAMILY_DEFAULTS, OPERATIONAL, RESUMABLE_CHANGES, TrainConfig, parse_overrides
from omnirecon.errors import InputError
from omnirecon.models.registry import _families, build_model, family_of, model_config_dict
from omnirecon.options import check_options
from omnirecon.outputs import swap_in
from omnirecon.preflight import check_train_views
from omnirecon.progress import progress_bar
from omnirecon.provenance import provenance


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


# ---------------------------------------------------------------------- the trainer
class Trainer:
    """Holds the run's state; ``run()`` trains from scratch or the latest checkpoint."""

    def __init__(self, cfg: TrainConfig, env: DistEnv):
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
                              cfg.resolution, cfg.scenes_in_memory, cfg.max_views, cfg.real_background)
        self.mix_bank = None
        """With ``--mix-resolution``: the same sources read at that size (:meth:`bank_at`)."""
        if cfg.mix_resolution:
            mixed = parse_sources(cfg.data, "train", **{**common, "resolution": cfg.mix_resolution})
            self.mix_bank = SceneBank(mixed, list(cfg.data_weights) if cfg.data_weights else None, cfg.mix_resolution,
                                      cfg.scenes_in_memory, cfg.max_views, cfg.real_background)
        if cfg.stereo_depth:
            for bank in (self.bank, self.mix_bank):
                if bank is not None:
                    bank.annotate = StereoPseudoDepth()
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

        check_options("train", c)  # every numeric option's range: omnirecon/options.py
        need(self.rays >= 1, f"--rays must be at least 1, got {self.rays}", "use e.g. --rays 256")
        need(c.mix_resolution == 0 or c.mix_resolution >= 8, f"--mix-resolution must be 0 (off) or at least 8 px, got "
             f"{c.mix_resolution}", "use e.g. --mix-resolution 64")
        need(self.lr > 0, f"--lr must be positive, got {self.lr}", "use e.g. --lr 5e-4")
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
        need(len(c.data) >= 1, "--data needs at least one source", "use e.g. --data synth:object")
        need(c.data_weights is None or (len(c.data_weights) == len(c.data) and all(w > 0 for w in c.data_weights)),
             f"--data-weights needs one positive weight per --data source ({len(c.data)})",
             "e.g. --data-weights 0.7 0.3")
        if self.out.exists() and not self.out.is_dir():
            raise InputError("run folder path is a file", self.out, "pass a folder for --out")
        from omnirecon.engine.checkpoint_check import resume_folder

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
        self.loss_module = LossModule(self.model, c.aux_weight, self.depth_weight, c.mask_weight)
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
            from omnirecon.engine.checkpoint_check import read_weights

            state = read_weights(latest / "model.safetensors", str(self.device))
            self.model.load_state_dict(state)
            load_optimizer_state(latest, self.opt)
            self.step = int(meta["step"])
            self.elapsed = float(meta["extra"].get("elapsed_s", 0.0))
            self.cpu_used = float(meta["extra"].get("cpu_s", 0.0))
            if meta["extra"].get("scaler"):
                self.scaler.load_state_dict(meta["extra"]["scaler"])
        elif c.init is not None:
            self.warm_start(Path(c.init))
        self.model_config = model_config_dict(self.model)
        check_train_views(self.bank, self.train_sources, max(self.cfg.num_views_range or (self.K,)))  # before any file
        if env.main:
            self.open_logs()

    def warm_start(self, ckpt: Path) -> None:
        """Load the weights of checkpoint folder ``ckpt`` (same preset and model config) into the fresh model."""
        ckpt = checkpoint_folder(ckpt)  # a path, or a shipped name such as ibrnet-tiny
        if not (ckpt / "model.safetensors").is_file() or not (ckpt / "meta.json").is_file():
            raise InputError("--init needs a checkpoint folder with model.safetensors and meta.json", ckpt,
                             "pass e.g. checkpoints/ibrnet-tiny or a run's checkpoints/final")
        meta = read_meta(ckpt)
        if meta.get("preset") != self.cfg.model:
            raise InputError(f"--init checkpoint is a {meta.get('preset')} model, not {self.cfg.model}", ckpt,
                             f"pass --model {meta.get('preset')} or a {self.cfg.model} checkpoint")
        try:
            self.model.load_state_dict(checkpoint_weights(ckpt, str(self.device)))
        except RuntimeError as e:
            raise InputError(f"--init weights do not fit the model ({str(e).splitlines()[0]})", ckpt,
                             "pass the same --model-overrides as the checkpoint's run (see its meta.json)") from e
        self.notes.append(f"warm start from {ckpt} (step {meta.get('step')}): fresh optimizer and schedule")

    def check_resume(self, meta: dict) -> None:
        saved = meta.get("train_config", {})
        now = self.config_dict()
        diff = [k for k in now if k not in OPERATIONAL | RESUMABLE_CHANGES and k in saved and saved[k] != now[k]]
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
        if saved.get("resolution", now["resolution"]) != now["resolution"]:
            self.notes.append(f"--resolution changed {saved['resolution']} -> {now['resolution']}: the run continues on "
                              "images of the new size (a coarse-to-fine schedule, e.g. 64 then 128)")
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

        self.setup()
        c = self.cfg
        for note in self.notes:
            self.say(f"note: {note}")
        last = min(c.steps, c.stop_at or c.steps)
        if self.step >= last or self.over_budget():
            self.say(f"nothing to do: the checkpoint in {self.out} is at step {self.step} after {self.elapsed:.0f} s "
                     "(raise --steps or --time-budget to train on)")
            return
        self.start_progress(last)
        self.terminated = False
        previous = self.catch_sigterm()
        try:
            self.loop(last)
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)

    def catch_sigterm(self):
        """Make SIGTERM end the loop after the current step (main thread only); returns the old handler."""
        if threading.current_thread() is not threading.main_thread():
            return None

        def stop(signum, frame):
            self.terminated = True

        return signal.signal(signal.SIGTERM, stop)

    def bank_at(self, s: int) -> SceneBank:
        """The scene bank of step ``s``: with ``--mix-resolution``, per scene (every ``--switch-every`` steps) the
        second size with odds ``--mix-share``, drawn from the seed of the scene's first step; else the one bank."""
        c = self.cfg
        if self.mix_bank is None:
            return self.bank
        gen = torch.Generator().manual_seed(step_seed(c.seed, (s - 1) // c.switch_every, self.env.rank, 3))
        return self.mix_bank if float(torch.rand(1, generator=gen)) < c.mix_share else self.bank

    def loop(self, last: int) -> None:
        c, env = self.cfg, self.env
        window = torch.zeros(4, dtype=torch.float64)  # loss, mse, steps, step seconds since the last log line
        t0 = time.perf_counter() - self.elapsed
        cpu0 = time.process_time() - self.cpu_used
        while self.step < last:
            s = self.step + 1
            t_step = time.perf_counter()
            gen = torch.Generator().manual_seed(step_seed(c.seed, s, env.rank))
            torch.manual_seed(step_seed(c.seed, s, env.rank, 1))  # model-internal draws (IBRNet jitter)
            bank = self.bank_at(s)
            ref = bank.choose(torch.Generator().manual_seed(step_seed(c.seed, (s - 1) // c.switch_every, env.rank, 2)))
            K, pool = self.views_at(s)
            batch = draw_batch(bank.get(ref), K, pool, self.rays, gen, c.foreground).to(self.device)
            loss, mse = self.optimise(s, batch)
            window += torch.tensor([loss, mse, 1.0, time.perf_counter() - t_step], dtype=torch.float64)
            self.step = s
            self.elapsed = time.perf_counter() - t0
            self.cpu_used = time.process_time() - cpu0
            stop = self.agree(self.over_budget() or self.terminated)
            end = stop or s == last
            if s % c.log_every == 0 or end:
                loss_sum, mse_sum, n, secs = self.reduce(window)  # sums over ranks
                secs = max(secs / env.world, 1e-9)  # ranks run side by side
                row = {"step": s, "loss": loss_sum / n, "psnr": psnr(mse_sum / n), "lr": self.opt.param_groups[0]["lr"],
                       "rays_per_s": n * self.rays / secs, "steps_per_s": n / env.world / secs,
                       "time": self.elapsed, "cpu_time": self.cpu_used, "scene": ref.name,
                       **({"resolution": bank.resolution} if self.mix_bank is not None else {})}
                self.log(row)
                window.zero_()
            if c.val_every and s % c.val_every == 0 and not end:
                self.validate(s)
            if c.ckpt_every and s % c.ckpt_every == 0 and not end:
                self.checkpoint(s)
            if stop:
                why = "SIGTERM received" if self.terminated else "budget reached"
                self.say(f"{why} at step {s} ({self.elapsed:.0f} s wall, {self.cpu_used:.0f} CPU s): checkpointed, "
                         "continue with --resume")
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
            loss, mse, _ = self.ddp(batch.sources, batch.rays, batch.rgb, batch.depth, batch.mask)
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
        if self.env.world == 1:
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

        from rich.progress import TextColumn

        self.pg = progress_bar(f"train {self.cfg.model}", "", TextColumn("{task.fields[info]}"), console=self.console,
                               transient=False)
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
                swap_in(tmp, ckdir / "final")  # the previous final or the new one, never neither
        self.barrier()

    def close(self) -> None:
        torch.set_num_threads(self.threads_before)
        self.stop_progress()
        if self.metrics is not None:
            self.metrics.close()
        if self.writer is not None:
            self.writer.close()
