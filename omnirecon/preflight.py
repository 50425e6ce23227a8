"""Checks run before a command starts working, for inputs that would otherwise be silently wrong:
a forced ``--format`` that does not fit the folder, ``--num-views`` above what a scene has, a
``--resolution`` of 0 that used to fall back to the default; and allocations that an option sizes, checked
against the memory the machine has (:func:`check_memory`) rather than against a fixed count."""

from __future__ import annotations

import importlib
from pathlib import Path

from omnirecon.errors import InputError
from omnirecon.memory import memory_bytes


def check_format(path: Path, format: str, readers: dict[str, str]) -> None:
    """InputError when the forced reader ``format`` does not recognise ``path`` (naming what does)."""
    if importlib.import_module(readers[format]).detect(path):
        return
    found = [name for name, module in readers.items() if importlib.import_module(module).detect(path)]
    what = f"it looks like {found[0]}" if found else "no reader recognises it"
    raise InputError(f"--format {format} does not fit this folder ({what})", path,
                     f"pass --format {found[0]}, or leave --format out" if found else
                     "point at the scene folder, or leave --format out to detect the format")


def check_resolution(value: int | None, flag: str = "--resolution") -> None:
    """``None`` (the protocol's default) or at least 8 px; 0 and negatives are refused, not replaced."""
    if value is not None and value < 8:
        raise InputError(f"{flag} must be at least 8 px, got {value}", None,
                         f"use e.g. {flag} 128, or leave it out for the default")


def check_planned(jobs: list[dict], records: list[dict], ks: list[int]) -> None:
    """InputError when no requested source count K runs on any scene (every pool smaller than every K),
    instead of writing empty result tables. A K skipped beside others that run is reported in the results
    (``skipped``) and in the printed summary."""
    if not jobs:
        missing = sorted(ks)
        pools = sorted({len(r["pool"]) for r in records})
        where = records[0]["path"] if len(records) == 1 and records[0]["path"] else None
        raise InputError(f"--num-views {missing[0]} exceeds the source pool of every scene (pool sizes {pools})",
                         where, f"pass --num-views {max(pools) if pools else 1} or fewer")


def check_train_views(bank, sources, k_max: int) -> None:
    """Load the first scene of each training source and refuse a ``k_max`` above its source views (its
    training views minus the target), before the run folder gets any file."""
    for src in sources:
        if not src:
            continue
        ps = bank.get(src[0])
        have = len(ps.targets) - 1
        if k_max > have:
            raise InputError(f"--num-views {k_max} but the scene has {len(ps.targets)} training views "
                             f"({have} sources per target)", ps.scene.path,
                             f"pass --num-views {have} or fewer, or train on scenes with more views")


def available_memory() -> int:
    """Bytes a new allocation can get now (:func:`omnirecon.memory.memory_bytes`: ``MemAvailable``, and no more than
    the address-space limit, ``ulimit -v``, leaves)."""
    return memory_bytes()[1]


def check_memory(need: float, option: str, fits, path: Path | None = None) -> None:
    """InputError naming ``option`` when an allocation of about ``need`` bytes exceeds :func:`available_memory`;
    ``fits(share)`` is a value of the option that needs ``share`` (< 1) of what this one needs."""
    avail = available_memory()
    if need <= avail:
        return
    raise InputError(f"{option} needs about {need / 2**30:.1f} GiB of memory, and {avail / 2**30:.1f} GiB is available",
                     path, f"use {option} {fits(0.5 * avail / need)} or more memory")
