"""Machine settings every command shares: device, CPU threads and rays per rendering chunk, and the
model a command runs (a checkpoint or the non-learned floor)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from omnirecon.chunk import pick_chunk
from omnirecon.engine.checkpoint import load_checkpoint
from omnirecon.engine.shipped import checkpoint_folder
from omnirecon.errors import InputError
from omnirecon.models.registry import build_model


def load_model(ckpt: Path | None, model: str | None, device: str = "cpu"):
    """The model of ``--ckpt`` or ``--model floor`` (exactly one). Returns ``(model, info)``."""

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
    net, meta = load_checkpoint(ckpt, device)
    info = {"name": meta["preset"], "preset": meta["preset"], "checkpoint": str(ckpt), "step": meta.get("step")}
    return net.eval(), info


def set_threads(threads: int | None) -> None:
    """Set torch's CPU thread count (``None`` keeps it)."""
    if threads is not None:
        if threads < 1:
            raise InputError(f"--threads must be at least 1, got {threads}", None, "use e.g. 1")
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
class MachineConfig(DeviceConfig):
    """Threads, device and the rendering chunk of a command that renders images."""

    chunk: int | None = None
    """Rays rendered per chunk: bounds memory (default: from the free memory, at most 4096; a one-line note
    when a given value would need more than 25% of the RAM)."""

    def __post_init__(self) -> None:
        self.chunk = pick_chunk(self.chunk)  # None: from the free memory
