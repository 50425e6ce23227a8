"""Machine settings every command shares: device, CPU threads and rays per rendering chunk, and the
model a command runs (a checkpoint or the non-learned floor): the option groups (``kw_only`` dataclasses a
command's configuration inherits, each field declared once; the others are in :mod:`omnirecon.options`) and
the functions that apply them."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import torch

from omnirecon.chunk import pick_chunk
from omnirecon.engine.checkpoint import folder_for_size, load_checkpoint, trained_long_side
from omnirecon.engine.shipped import checkpoint_folder, shipped_checkpoint
from omnirecon.errors import InputError
from omnirecon.models.guided import GuidedOptions
from omnirecon.models.registry import build_model
from omnirecon.options import check_value


def load_model(ckpt: Path | None, model: str | None, device: str = "cpu", long_side: int | None = None):
    """The model of ``--ckpt`` or ``--model floor`` (exactly one); with ``long_side`` (px, the size the command
    renders at), the checkpoint's weights trained nearest that size (``checkpoint.folder_for_size``). Returns
    ``(model, info)``; ``info["checkpoint"]`` is the folder whose weights were loaded."""

    if (ckpt is None) == (model is None):
        raise InputError("give exactly one of --ckpt or --model", None,
                         "--ckpt CHECKPOINT_FOLDER for a trained model, or --model floor")
    if model is not None:
        if model != "floor":
            raise InputError(f"--model {model} has no weights", None, "only the non-learned --model floor runs "
                             "without a checkpoint; pass --ckpt for a trained model")
        return build_model("floor").to(device).eval(), {"name": "floor", "preset": "floor", "checkpoint": None}
    ckpt = checkpoint_folder(ckpt)
    if not ckpt.exists():
        raise InputError("checkpoint folder not found", ckpt, "pass e.g. --ckpt omnirecon-tiny (a shipped checkpoint)")
    chosen = folder_for_size(ckpt, long_side)
    net, meta = load_checkpoint(chosen, device)
    info = {"name": meta["preset"], "preset": meta["preset"], "checkpoint": str(chosen), "step": meta.get("step"),
            **({"trained_long_side": trained_long_side(meta)} if chosen != ckpt else {})}
    return net.eval(), info


def set_threads(threads: int | None) -> None:
    """Set torch's CPU thread count (``None`` keeps it)."""
    if threads is not None:
        check_value("threads", threads)  # its rule: omnirecon/options.py
        torch.set_num_threads(threads)


def pick_device(device: str) -> str:
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(f"--device {device} but CUDA is not available", None, "use --device cpu")
    return device


@dataclass(kw_only=True)
class ThreadsConfig:
    """The CPU share of a command (every command's configuration inherits it)."""

    threads: int | None = None
    """torch CPU threads (default: torch's choice). Use 1 when other jobs share the cores: on a busy
    2-core machine 2 threads ran the floor several times slower than 1."""


@dataclass(kw_only=True)
class DeviceConfig(ThreadsConfig):
    """Threads and the device a command runs its model on."""

    device: str = "auto"
    """cpu, cuda or auto (cuda when available)."""

    def apply(self) -> str:
        """Set the thread count; return the device to use."""
        set_threads(self.threads)
        return pick_device(self.device)


@dataclass(kw_only=True)
class ChunkConfig(ThreadsConfig):
    """Threads and the rendering chunk of a command that renders on the CPU."""

    chunk: int | None = None
    """Rays rendered per chunk: bounds memory (default: from the free memory, at most 4096; a one-line note
    when a given value would need more than 25% of the RAM)."""

    def __post_init__(self) -> None:
        self.chunk = pick_chunk(self.chunk)  # None: from the free memory


@dataclass(kw_only=True)
class MachineConfig(DeviceConfig, ChunkConfig):
    """Threads, device and the rendering chunk of a command that renders images."""


@dataclass(kw_only=True)
class ModelChoice:
    """A command that runs a checkpoint or the non-learned floor (exactly one: :func:`load_model`)."""

    ckpt: Path | None = None
    """Checkpoint folder written by `omnirecon train` (holds meta.json and model.safetensors), or a shipped
    checkpoint's name (e.g. omnirecon-tiny)."""
    model: Literal["floor"] | None = None
    """A non-learned model instead of a checkpoint: `floor` is the plane-sweep baseline."""


@dataclass(kw_only=True)
class CheckpointInput:
    """A command that needs a trained checkpoint (which models it takes: the command's description)."""

    ckpt: Path
    """Checkpoint folder written by `omnirecon train`, or a shipped checkpoint's name (e.g. omnirecon-tiny)."""


@dataclass(kw_only=True)
class ShippedCheckpoint:
    """A command that runs Omni-Recon, the shipped one unless told."""

    ckpt: Path = shipped_checkpoint("omnirecon-tiny")
    """Omni-Recon checkpoint folder or shipped name (default: the shipped omnirecon-tiny)."""


@dataclass(kw_only=True)
class GuidedRendering:
    """A command whose volumetric renders may be surface-guided."""

    guided: GuidedOptions = field(default_factory=GuidedOptions)
    """Surface-guided rendering (``--guided.on``): each ray sampled in a band around a prior depth from a low-resolution
    render, the full path where the prior is missing or untrusted; changes the renders, recorded with them."""
