"""Checks that turn every bad checkpoint into a one-line :class:`InputError` naming the file and the fix.

* :func:`checked_meta` reads ``meta.json`` and checks ``preset`` (a known name) and ``model_config``
  (a dict whose keys are options of the preset's config class and whose values have its field types).
* :func:`read_weights` reads a safetensors file, telling a missing file from an unreadable or truncated
  one, and refuses NaN/Inf in floating-point tensors (they would render all-black frames).
* :func:`safetensors_problem` checks a safetensors file's header against its size without reading the
  tensors (cheap enough to check every checkpoint of a run folder).
* :func:`resume_folder` picks the checkpoint a ``train --resume`` continues from: ``checkpoints/latest``
  when it is intact, else the newest intact ``step_*`` beside it (with a note saying which and why).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import struct
import types
import typing
from pathlib import Path

from omnirecon.errors import InputError

MAX_INT = 1 << 20  # above every cap of _int_cap; the per-field cap is checked after the types
REWRITE = "rewrite the file from a training run (omnirecon train writes it), or restore it from a backup"


def _config_class(preset: str, source: Path):
    from omnirecon.models.registry import _families, preset_names

    for _, cfg_cls, presets in _families().values():
        if preset in presets:
            return cfg_cls
    raise InputError(f"unknown preset {preset!r}", source, f"set \"preset\" to one of: {', '.join(preset_names())}")


def _type_ok(value, annotation) -> bool:
    """Whether JSON ``value`` fits the dataclass field type ``annotation`` (int, float, bool, str, Literal,
    tuple[...] as a JSON list, Optional/Union)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= MAX_INT
    if annotation is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if annotation is str:
        return isinstance(value, str)
    if origin is typing.Literal:
        return any(value == a and type(value) is type(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return any(_type_ok(value, a) for a in args)
    if annotation is type(None):
        return value is None
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_type_ok(v, args[0]) for v in value)
        return len(value) == len(args) and all(_type_ok(v, a) for v, a in zip(value, args))
    return True  # a type this check does not know: the model's own constructor judges it


def checked_meta(folder: Path) -> dict:
    """``meta.json`` of checkpoint ``folder``, with ``preset`` and ``model_config`` checked (InputError
    naming ``meta.json`` otherwise)."""
    from omnirecon.data.io import read_json

    folder = Path(folder)
    source = folder / "meta.json"
    if not source.is_file():
        raise InputError("not a checkpoint folder (no meta.json)", folder,
                         "pass a folder written by `omnirecon train` (e.g. outputs/train/run/checkpoints/latest)")
    try:
        meta = read_json(source)
    except OSError as e:
        raise InputError(f"cannot read meta.json ({e.strerror or e})", source, "make the file readable") from e
    if not isinstance(meta, dict):
        raise InputError(f"meta.json must hold a JSON object, got {type(meta).__name__}", source, REWRITE)
    preset = meta.get("preset")
    if not isinstance(preset, str):
        raise InputError("meta.json lacks a \"preset\" name" if preset is None else
                         f"\"preset\" must be a string, got {type(preset).__name__}", source, REWRITE)
    cfg_cls = _config_class(preset, source)
    config = meta.get("model_config")
    if not isinstance(config, dict):
        raise InputError("meta.json lacks \"model_config\"" if config is None else
                         f"\"model_config\" must be an object, got {type(config).__name__}", source, REWRITE)
    hints = typing.get_type_hints(cfg_cls)
    names = {f.name for f in dataclasses.fields(cfg_cls)}
    unknown = sorted(set(config) - names)
    if unknown:
        raise InputError(f"model_config has unknown option(s) {', '.join(map(repr, unknown))} for {preset}", source,
                         f"remove them (options are: {', '.join(sorted(names))}) or use the code version that "
                         "wrote the checkpoint")
    for key, value in config.items():
        if not _type_ok(value, hints[key]):
            want = getattr(hints[key], "__name__", None) or str(hints[key]).replace("typing.", "")
            raise InputError(f"model_config.{key} = {json.dumps(value)[:40]} is not a valid {want}", source,
                             f"give {key} a value of type {want} (the preset's is "
                             f"{getattr(_preset_config(preset), key)!r}) or {REWRITE}")
    for key, value in config.items():
        cap = _int_cap(preset, key)
        ints = [v for v in (value if isinstance(value, (list, tuple)) else [value])
                if isinstance(v, int) and not isinstance(v, bool)]
        if cap is not None and any(v > cap for v in ints):
            raise InputError(f"model_config.{key} = {json.dumps(value)[:40]} is above {cap} (8x the largest preset "
                             "value; it would only exhaust memory)", source,
                             f"use the preset's {getattr(_preset_config(preset), key)!r} or {REWRITE}")
    step = meta.get("step", 0)
    if not isinstance(step, int) or isinstance(step, bool) or step < 0:
        raise InputError(f"\"step\" must be a non-negative integer, got {json.dumps(step)[:40]}", source, REWRITE)
    for key in ("extra", "train_config"):
        if meta.get(key) is not None and not isinstance(meta[key], dict):
            raise InputError(f"\"{key}\" must be an object, got {type(meta[key]).__name__}", source, REWRITE)
    return meta


def _int_cap(preset: str, key: str) -> int | None:
    """8x the largest integer any preset of ``preset``'s family has in field ``key`` (at least 64);
    ``None`` for fields without integers."""
    from omnirecon.models.registry import _families

    presets = next(p for _, _, p in _families().values() if preset in p)
    values = []
    for cfg in presets.values():
        v = getattr(cfg, key, None)
        items = v if isinstance(v, (list, tuple)) else [v]
        values += [x for x in items if isinstance(x, int) and not isinstance(x, bool)]
    return max(64, 8 * max(values)) if values else None


def _preset_config(preset: str):
    from omnirecon.models.registry import _families

    return next(p[preset] for _, _, p in _families().values() if preset in p)


def build_checked(meta: dict, folder: Path):
    """The model of a :func:`checked_meta` dict; a config the model refuses becomes an InputError."""
    import torch

    from omnirecon.models.registry import build_model

    source = Path(folder) / "meta.json"
    try:
        with torch.device("meta"):  # shapes only, no memory: a huge model_config is refused before allocating
            probe = build_model(meta["preset"], meta["model_config"])
        header = safetensors_header(Path(folder) / "model.safetensors")
        if header is not None:
            for key, t in probe.state_dict().items():
                want = header.get(key, {}).get("shape") if isinstance(header.get(key), dict) else None
                if want is not None and list(want) != list(t.shape):
                    raise InputError(f"model_config does not match model.safetensors ({key}: {list(t.shape)} vs "
                                     f"{list(want)} in the weights)", source,
                                     f"restore the model_config that trained these weights, or {REWRITE}")
        return build_model(meta["preset"], meta["model_config"])
    except InputError:
        raise
    except (ValueError, TypeError, RuntimeError, AssertionError, ZeroDivisionError, OverflowError,
            NotImplementedError, IndexError, KeyError) as e:
        raise InputError(f"model_config cannot build {meta['preset']} ({type(e).__name__}: {str(e)[:80]})",
                         source, REWRITE) from e


def safetensors_header(path: Path) -> dict | None:
    """The JSON header of an intact safetensors file (``None`` when :func:`safetensors_problem` finds one)."""
    if safetensors_problem(path) is not None:
        return None
    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
        return json.loads(f.read(n))


def safetensors_problem(path: Path) -> str | None:
    """Why the safetensors file ``path`` cannot be read (missing, unreadable, truncated, bad header), or
    ``None``. Reads only the header."""
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return "is missing"
    if not path.is_file():
        return "is not a regular file (a dangling link or a folder)"
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(8)
            if len(head) < 8:
                return f"is unreadable: truncated ({size} bytes, no header)"
            (n,) = struct.unpack("<Q", head)
            if n > size - 8 or n > 100_000_000:
                return f"is unreadable: truncated or corrupt (header of {n} bytes in a {size}-byte file)"
            header = json.loads(f.read(n))
    except PermissionError:
        return "is unreadable: permission denied"
    except OSError as e:
        return f"is unreadable ({e.strerror or e})"
    except (json.JSONDecodeError, UnicodeDecodeError):
        return "is unreadable: corrupt header"
    if not isinstance(header, dict):
        return "is unreadable: corrupt header"
    end = 0
    for name, info in header.items():
        if name == "__metadata__":
            continue
        offsets = info.get("data_offsets") if isinstance(info, dict) else None
        if not (isinstance(offsets, list) and len(offsets) == 2 and all(isinstance(o, int) for o in offsets)):
            return f"is unreadable: corrupt header entry {name!r}"
        end = max(end, offsets[1])
    if 8 + n + end != size:
        return f"is unreadable: truncated ({size} bytes, the header needs {8 + n + end})"
    return None


def read_weights(path: Path, device: str = "cpu", finite: bool = True) -> dict:
    """Tensors of the safetensors file ``path``; InputError when missing, unreadable or (``finite``)
    holding NaN/Inf in a floating-point tensor."""
    import torch
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    path = Path(path)
    problem = safetensors_problem(path)
    if problem is not None:
        fix = ("copy the checkpoint's " + path.name + " back" if problem == "is missing" else
               "the file is damaged: restore it, or resume from an earlier step_* checkpoint")
        raise InputError(f"{path.name} {problem}", path, fix)
    try:
        state = load_file(str(path), device=str(device))
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise InputError(f"{path.name} is unreadable ({str(e)[:100]})", path,
                         "the file is damaged: restore it, or resume from an earlier step_* checkpoint") from e
    if finite:
        for name, t in state.items():
            if t.is_floating_point() and not bool(torch.isfinite(t).all()):
                bad = int((~torch.isfinite(t)).sum())
                raise InputError(f"tensor {name!r} holds {bad} NaN/Inf value(s); the model would render garbage",
                                 path, "use an earlier checkpoint (training diverged or the file is damaged)")
    return state


def checkpoint_problem(folder: Path, optimizer: bool = True) -> str | None:
    """Why ``folder`` cannot be resumed from (``None`` when intact): meta.json, weights and (``optimizer``)
    optimizer state, checked without loading tensors."""
    folder = Path(folder)
    if folder.is_symlink() and not folder.exists():
        return "is a dangling link"
    if not folder.is_dir():
        return "is missing"
    try:
        meta = checked_meta(folder)
    except InputError as e:
        return e.what
    for name in ["model.safetensors"] + (["optimizer.safetensors"] if optimizer else []):
        problem = safetensors_problem(folder / name)
        if problem:
            return f"{name} {problem}"
    if optimizer and not isinstance(meta.get("optimizer"), dict):
        return "has no optimizer state in meta.json (not a training checkpoint)"
    return None


def resume_folder(run: Path, notes: list[str] | None = None) -> Path:
    """The checkpoint folder ``train --resume`` continues from in run folder ``run``: ``checkpoints/latest``
    if intact, else the newest intact ``checkpoints/step_*`` (a line in ``notes`` says which and why).
    InputError when there is nothing intact to resume from."""
    ckdir = Path(run) / "checkpoints"
    latest = ckdir / "latest"
    steps = sorted((p for p in ckdir.glob("step_*") if p.is_dir()), reverse=True) if ckdir.is_dir() else []
    if not latest.exists() and not latest.is_symlink() and not steps:
        raise InputError("nothing to resume: no checkpoints/latest in the run folder", run,
                         "drop --resume to start a new run, or point --out at an earlier run")
    why = checkpoint_problem(latest)
    if why is None:
        return latest
    for cand in steps:
        if checkpoint_problem(cand) is None:
            if notes is not None:
                notes.append(f"checkpoints/latest{_points_to(latest)}: {why}; resuming from the newest intact "
                             f"checkpoint, {cand.name}")
            return cand
    raise InputError(f"checkpoints/latest{_points_to(latest)}: {why}, and no step_* checkpoint beside it is intact",
                     latest,
                     "restore the checkpoint files, or drop --resume and start a new run in a new --out")


def _points_to(link: Path) -> str:
    return f" (-> {os.readlink(link)})" if link.is_symlink() else ""


def load_optimizer_checked(folder: Path, optimizer) -> None:
    """Restore optimizer state of checkpoint ``folder`` (see :func:`omnirecon.engine.checkpoint.load_optimizer_state`)
    with every failure an InputError naming the file."""
    meta = checked_meta(folder)
    opt = meta.get("optimizer")
    source = Path(folder) / "optimizer.safetensors"
    if not isinstance(opt, dict):
        raise InputError("checkpoint has no optimizer state", folder, "resume from a training checkpoint")
    tensors = read_weights(source, finite=False)
    try:
        state = {int(pid): {n: tensors[f"{pid}.{n}"] for n in names} for pid, names in opt["state_keys"].items()}
        optimizer.load_state_dict({"state": state, "param_groups": opt["param_groups"]})
    except (KeyError, ValueError, TypeError, AttributeError, RuntimeError) as e:
        raise InputError(f"optimizer state does not match the model ({type(e).__name__}: {str(e)[:80]})", source,
                         "resume from an intact step_* checkpoint, or start a new run") from e
