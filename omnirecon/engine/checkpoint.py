"""Checkpoints: a folder with safetensors weights, JSON metadata and optimizer state.

Layout of ``DIR`` (the files are one set: all written to temporary names first, then renamed together,
``meta.json`` last, with Ctrl-C held back (:func:`omnirecon.outputs.atomic_files`), so an interrupted save
leaves the previous checkpoint or the new one)::

    model.safetensors        weights
    optimizer.safetensors    optimizer tensors (training checkpoints only)
    meta.json                {"preset", "model_config", "step", "train_config", "optimizer": {param_groups,
                              state keys}, "extra": {...}, "provenance": {...}}
    sizes/<px>/              optional: the same model trained further at a <px> long side (model.safetensors: the
                             tensors that differ from the own weights, :func:`checkpoint_weights`; meta.json);
                             :func:`folder_for_size` picks between them
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
from pathlib import Path

import torch
from safetensors.torch import save_file
from torch import nn

from omnirecon.data.io import write_json
from omnirecon.engine.held import held
from omnirecon.engine.shipped import checkpoint_folder
from omnirecon.errors import InputError
from omnirecon.models.registry import model_config_dict
from omnirecon.outputs import atomic_files


def save_checkpoint(folder: Path, model, preset: str, step: int = 0, optimizer: torch.optim.Optimizer | None = None,
                    train_config: dict | None = None, extra: dict | None = None, provenance: dict | None = None) -> None:

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    module = model.module if hasattr(model, "module") else model  # unwrap DDP
    state = {k: v.detach().contiguous().cpu() for k, v in module.state_dict().items()}
    tensors, opt_meta = {}, None
    if optimizer is not None:
        sd = optimizer.state_dict()
        keys = {}
        for pid, st in sd["state"].items():
            for name, value in st.items():
                t = value if torch.is_tensor(value) else torch.tensor(value)
                tensors[f"{pid}.{name}"] = t.detach().contiguous().cpu()
                keys.setdefault(str(pid), []).append(name)
        opt_meta = {"param_groups": sd["param_groups"], "state_keys": keys}
    meta = {"preset": preset, "model_config": model_config_dict(module), "step": step,
            "train_config": train_config or {}, "optimizer": opt_meta, "extra": extra or {},
            "provenance": provenance or {}}
    # weights, optimizer state and meta.json are one set: all written first, then renamed together with
    # Ctrl-C held back, so an interrupt leaves the previous checkpoint or the new one, never a mix
    names = ["model.safetensors", *(["optimizer.safetensors"] if optimizer is not None else []), "meta.json"]
    with atomic_files([folder / n for n in names]) as tmps:
        save_file(state, str(tmps[0]))
        if optimizer is not None:
            save_file(tensors, str(tmps[1]))
        write_json(tmps[-1], meta)


def read_meta(folder: Path) -> dict:
    """The checked ``meta.json`` of checkpoint ``folder`` (a path, or a shipped name: :func:`checkpoint_folder`)."""
    from omnirecon.engine.checkpoint_check import checked_meta

    return checked_meta(checkpoint_folder(folder))


SIZES_FOLDER = "sizes"
"""Sub-folder of a checkpoint holding its weights trained at other image sizes, one checkpoint folder per long side
(``sizes/256/``): a model's image encoder and aggregator see finer detail per pixel at a larger size, and weights
trained at the size they render at score higher there (BENCHMARKS "ibrnet-tiny trained further at 256 px")."""


def trained_long_side(meta: dict) -> int | None:
    """The long side (px) a checkpoint's weights were last trained at (``train_config.resolution``; None: not
    recorded)."""
    size = (meta.get("train_config") or {}).get("resolution")
    return size if isinstance(size, int) and not isinstance(size, bool) and size > 0 else None


def sized_folders(folder: Path) -> dict[int, Path]:
    """The weights of checkpoint ``folder`` by the long side (px) they were trained at: the folder's own (when its
    meta.json records its training size) and each ``sizes/<px>/`` sub-folder holding a meta.json."""
    folder = Path(folder)
    out = {int(p.name): p for p in sorted((folder / SIZES_FOLDER).glob("*"))
           if p.name.isdigit() and (p / "meta.json").is_file()}
    own = trained_long_side(read_meta(folder))
    if own is not None:
        out[own] = folder  # the folder's own weights win a clash with a sub-folder of the same size
    return out


def folder_for_size(folder: Path, long_side: int | None) -> Path:
    """The checkpoint folder of ``folder``'s weights (:func:`sized_folders`) trained at the size nearest
    ``long_side`` px, as a ratio (128 lies as near 64 as 256); a tie, ``long_side=None`` or a folder without
    ``sizes/`` gives the folder's own weights."""
    folder = checkpoint_folder(folder)
    if long_side is None or not (Path(folder) / SIZES_FOLDER).is_dir():
        return folder
    sizes = sized_folders(folder)
    if not sizes:
        return folder
    own = trained_long_side(read_meta(folder))
    distance = {px: abs(math.log(long_side / px)) for px in sizes}
    best = min(distance.values())
    near = [px for px, d in distance.items() if d - best < 1e-9]
    return folder if own in near else sizes[min(near)]


def checkpoint_weights(folder: Path, device: str | torch.device = "cpu") -> dict:
    """The state dict of checkpoint ``folder``: its ``model.safetensors``; for a ``sizes/<px>/`` folder, which holds
    only the tensors that differ from the checkpoint's own (a frozen image encoder is shared), those over the own
    weights. Missing, unreadable or non-finite weights: InputError naming the file."""
    from omnirecon.engine.checkpoint_check import read_weights

    folder = Path(folder)
    state = read_weights(folder / "model.safetensors", str(device))
    if folder.parent.name == SIZES_FOLDER and (folder.parent.parent / "model.safetensors").is_file():
        state = {**read_weights(folder.parent.parent / "model.safetensors", str(device)), **state}
    return state


def size_delta(own: dict, sized: dict) -> dict:
    """The tensors of state dict ``sized`` that differ from ``own``'s: what a ``sizes/<px>/`` folder stores."""
    return {k: v for k, v in sized.items() if k not in own or own[k].shape != v.shape or not torch.equal(own[k], v)}


def load_checkpoint(folder: Path, device: str | torch.device = "cpu", long_side: int | None = None):
    """Rebuild the model from ``folder`` (a path, or a shipped name: :func:`checkpoint_folder`); with ``long_side``
    (px, the size the caller renders at), from the weights trained nearest that size (:func:`folder_for_size`).
    Returns ``(model, meta)``; ``meta`` is that of the weights loaded (a ``sizes/<px>/`` folder's own)."""
    folder = folder_for_size(folder, long_side)
    return held("checkpoint", (str(Path(folder).resolve()), str(device)), lambda: _load_checkpoint(folder, device))


def _load_checkpoint(folder: Path, device: str | torch.device):
    from omnirecon.engine.checkpoint_check import build_checked

    meta = read_meta(folder)
    model = build_checked(meta, folder)
    state = checkpoint_weights(folder, device)
    try:
        missing, unexpected = model.load_state_dict(state, strict=False)
    except RuntimeError as e:  # shape mismatch
        missing, unexpected = [str(e).split("\n")[1].strip()[:80] if "\n" in str(e) else str(e)[:80]], []
    if missing or unexpected:
        raise InputError(f"weights do not match {meta['preset']} (missing {missing[:3]}, unexpected {unexpected[:3]})",
                         folder / "model.safetensors", "use the code version that wrote the checkpoint")
    return model.to(device), meta


def fingerprint(folder: Path, ignore=()) -> dict:
    """Identify a checkpoint for results files: ``{"path", "preset", "step", "sha256"}``, where ``sha256``
    is the first 16 hex digits of the SHA-256 of the weights file followed by the model config (sorted
    JSON), so a page built from stored results can tell whether they were measured with the checkpoint
    that ships now: new weights or a changed render option (e.g. GPNR's ``output``) both count.

    ``ignore``: model-config keys left out of the hash, for results that do not depend on them (the mesh
    path reads no volumetric render option: :data:`VOLUMETRIC_ONLY`)."""
    import hashlib

    folder = Path(folder)
    meta = read_meta(folder)
    h = hashlib.sha256((folder / "model.safetensors").read_bytes())
    config = {k: v for k, v in meta.get("model_config", {}).items() if k not in set(ignore)}
    h.update(json.dumps(config, sort_keys=True).encode())
    return {"path": str(folder), "preset": meta.get("preset"), "step": meta.get("step"), "sha256": h.hexdigest()[:16]}

VOLUMETRIC_ONLY = ("render_samples", "render_bf16", "render_fine_pass", "forward_box", "render_views")
"""Model-config keys only the volumetric path reads: the per-checkpoint render options
(``omnirecon.models.registry.RENDER_OPTIONS``) and Omni-Recon's geometry-volume box for forward scenes
(``forward_box``: the feature volume, not the appearance maps). The mesh path (2-D encoder maps, appearance
branch, fine-tuning of both) reads none of them, so results of the mesh path alone are compared with the
shipped checkpoint without them (``bench.report.common.stale_note``'s ``ignore``)."""

VIEW_CAP = ("render_views",)
"""Model-config keys read only when a view is rendered from more sources than the cap they set (the shipped
omnirecon-tiny: 4): results measured at K = 3 do not depend on them (``stale_note``'s ``ignore``)."""


def ignoring(folder: Path, ignore: tuple[str, ...] = VOLUMETRIC_ONLY) -> dict:
    """What a results file records besides :func:`fingerprint` so that a page can compare it with the shipped
    checkpoint without the config keys ``ignore``: ``sha256_ignoring`` and ``ignored_keys``."""
    return {"sha256_ignoring": fingerprint(folder, ignore)["sha256"], "ignored_keys": list(ignore)}


def load_optimizer_state(folder: Path, optimizer: torch.optim.Optimizer) -> None:
    """Restore optimizer state saved by :func:`save_checkpoint` into ``optimizer``."""
    from omnirecon.engine.checkpoint_check import load_optimizer_checked

    load_optimizer_checked(folder, optimizer)


def dumps(obj) -> str:
    return json.dumps(obj, indent=1, default=str)


def param_digest(model: nn.Module) -> str:
    """SHA-256 of every parameter's bytes, in state-dict order."""
    h = hashlib.sha256()
    for k, v in model.state_dict().items():
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


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
