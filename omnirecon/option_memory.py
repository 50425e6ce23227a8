"""Memory a command's sizes would take, checked before any work (:func:`omnirecon.options.check_options`): an
estimate per command (:data:`MEMORY`) of what each size option allocates, against a share (:data:`SHARE`) of the
memory available now; a size that does not fit is refused with the largest value that does. (An allocation a run
sizes from its input, e.g. the TSDF grid: :func:`omnirecon.preflight.check_memory`.)"""

from __future__ import annotations

from typing import Callable

from omnirecon.errors import InputError
from omnirecon.memory import memory_bytes

SHARE = 0.5
"""A run may plan on at most this share of the memory available when it starts."""

# Each estimate returns ``[(flag, shown, value, bytes_of)]``: ``bytes_of(v)`` is the memory the run allocates
# when the option is ``v`` and the others are as given (it grows with ``v``, so the limit can be solved for).
# Only sizes the command allocates as asked are estimated: an image reader's ``--resolution`` never exceeds
# the photos' own size, so it is checked by its range alone.
Need = tuple[str, str, int, Callable[[int], float]]

SYNTH_BYTES_PER_PIXEL = 2_500
"""Peak memory of procedural rendering per image pixel (synth 256 vs 768 px, 2 views: 0.49 vs 1.71 GB)."""
FEATURE_BYTES_PER_PIXEL = 512
"""Encoded source views: feature maps and image pyramids per source pixel (estimate)."""
FRAME_BYTES = 1_024
"""Per frame of a camera path: poses, source lists and the cameras.json record (render --frames 1e8 grew
to 21 GB, ~210 bytes per frame, before anything was written)."""
RAY_BYTES = 140_000
"""A rendered ray (omnirecon.chunk's measurement)."""
TRAIN_BYTES_PER_RAY = 3 * RAY_BYTES
"""A training ray: the forward's activations kept for the backward, with gradients (estimate)."""
FINETUNE_BYTES_PER_RAY_VIEW = 1_000
"""A fine-tuning pixel of the mesh path, per source view: one surface point through the appearance
branch, forward and backward (measured ~600 bytes per pixel and view with K = 3; margin for larger K)."""


def _sq(v: int) -> float:
    return float(v) * float(v)


def _frames(c) -> list[Need]:
    return [("--frames", str(c.frames), c.frames, lambda v: v * FRAME_BYTES)]


def _synth(c) -> list[Need]:
    workers = min(c.num_scenes, c.workers or 1)
    return [("--resolution", str(c.resolution), c.resolution, lambda v: _sq(v) * SYNTH_BYTES_PER_PIXEL * workers),
            ("--views", str(c.views), c.views, lambda v: v * _sq(c.resolution) * 4 * 12)]


def _bench(c) -> list[Need]:
    per_px = SYNTH_BYTES_PER_PIXEL + c.views * FEATURE_BYTES_PER_PIXEL
    if c.size:
        w, h = c.size
        return [("--size", f"{w} {h}", max(w, h), lambda v: _sq(v) * per_px)]
    return [("--resolution", str(c.resolution), c.resolution, lambda v: _sq(v) * per_px),
            ("--source-resolution", str(c.source_resolution), c.source_resolution, lambda v: _sq(v) * per_px),
            ("--rays", str(c.rays), c.rays, lambda v: v * RAY_BYTES)]


def _train(c) -> list[Need]:
    return [("--rays", str(c.rays), c.rays, lambda v: v * TRAIN_BYTES_PER_RAY)] if c.rays else []


def _finetune(c) -> list[Need]:
    views = max(c.num_views, len(c.views or ()))
    return [("--rays", str(c.rays), c.rays, lambda v: v * views * FINETUNE_BYTES_PER_RAY_VIEW)]


MEMORY: dict[str, Callable[[object], list[Need]]] = {
    "render": _frames, "reconstruct": _frames, "demo": _frames, "synth": _synth, "bench": _bench,
    "train": _train, "finetune": _finetune,
}


def _gb(b: float) -> str:
    return f"{b / 1e9:.1f} GB"


def check_sizes(needs: list[Need], available: int | None = None) -> None:
    available = memory_bytes()[1] if available is None else available
    budget = SHARE * available
    for flag, shown, value, bytes_of in needs:
        need = bytes_of(value)
        if need <= budget:
            continue
        lo, hi = 0, int(value)  # the largest value that fits: bytes_of grows with the value
        while lo < hi:
            mid = (lo + hi + 1) // 2
            lo, hi = (mid, hi) if bytes_of(mid) <= budget else (lo, mid - 1)
        what = " with a long side of" if flag == "--size" else ""
        fix = f"pass {flag}{what} {lo} or less" if lo >= 1 else "free memory, or lower the other sizes"
        raise InputError(f"{flag} {shown} needs about {_gb(need)} of memory (estimate), more than the "
                         f"{_gb(budget)} a run may use here ({SHARE:.0%} of the {_gb(available)} available now)",
                         None, fix)
