"""``omnirecon train``'s configuration: the fields a run records in ``config.json`` and ``meta.json``,
per-family defaults, and ``--model-overrides`` parsing. The trainer is :mod:`omnirecon.engine.train`."""

from __future__ import annotations

import dataclasses
import json
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from omnirecon.engine.machine import DeviceConfig
from omnirecon.errors import InputError
from omnirecon.options import ImageSize, OutFolder, Resumes, SceneCache, Seeded, Steps, ViewLimit, command_defaults

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
RESUMABLE_CHANGES = {"num_views_range", "resolution"}
"""Training flags a ``--resume`` may change (with a note): the view-count distribution, and the image size
(training at 64 px, then continuing at 128)."""


@dataclass
@command_defaults(resolution=64, cache=Path("outputs/cache/synth"))
class TrainConfig(OutFolder, Seeded, SceneCache, ImageSize, ViewLimit, Resumes, Steps, DeviceConfig):
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
    stereo_depth: bool = False
    """Pseudo ground truth for real scenes without depths: confident classical-stereo depth
    (:func:`omnirecon.mesh.stereo.stereo_depths` among the scene's training views, at the training
    resolution, kept where every pair agrees), supervised like known depth with ``--depth-weight``."""
    mask_weight: float = 0.0
    """Weight of the mask loss: squared error of the accumulated opacity (both passes) against the object
    mask, on scenes that have masks and for models that render ``acc`` (IBRNet, Omni-Recon). Use it where
    the background is empty (see :func:`omnirecon.engine.losses.mask_loss`); 0 disables it."""
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
    real_background: Literal["white", "black", "random"] = "white"
    """Background behind the objects of training scenes read from RGBA images (e.g. Blender's lego and chair; the
    alpha is the object's coverage): ``white`` as read; ``black``; ``random``: per step white, black or a uniform
    random flat colour (equal odds, drawn from the step's seed). The target and its sources share the colour;
    procedural scenes, photos without alpha and validation are unchanged."""
    switch_every: int = 10
    """Steps spent on one scene before drawing the next."""
    mix_resolution: int = 0
    """With a value > 0, a share (``--mix-share``) of the scenes drawn is read at this long side (px) instead of
    ``--resolution``: a second scene bank over the same sources and weights (procedural scenes generated at that size in
    ``--cache``), drawn per scene (every ``--switch-every`` steps, from the step's seed), so one run trains at two sizes.
    Validation stays at ``--resolution``. 0: every step at ``--resolution``."""
    mix_share: float = 0.5
    """With ``--mix-resolution``: the share of scenes drawn at that size (0-1)."""
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
    init: Path | None = None
    """Warm start: a checkpoint folder (model.safetensors + meta.json of the same preset and model config, e.g.
    checkpoints/ibrnet-tiny) whose weights the run starts from; the optimizer, the step count and the
    learning-rate schedule start fresh (fine-tuning a shipped model on a new data mix). Ignored on --resume,
    which continues from the run's own checkpoint."""
    stop_at: int | None = None
    """Stop (and checkpoint) after this step without finishing the schedule; continue with --resume."""
    amp: Literal["none", "bf16", "fp16"] = "none"
    """Mixed precision autocast (CUDA only)."""
    time_budget: float | None = None
    """Seconds of training (summed over resumed runs) after which to checkpoint and stop."""
    cpu_budget: float | None = None
    """CPU seconds of this process (all its threads, summed over resumed runs) after which to checkpoint and
    stop: a budget that other jobs on the machine do not shrink (2 cores x 20 min = 2400)."""
    progress: bool = True
    """Show the progress bar."""


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
