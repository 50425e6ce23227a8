"""Reads a long run holds in memory (``reconstruct``'s :class:`~omnirecon.workflows.reconstruct.Capture`).

Inside :func:`holding`, a scene folder read with the same options (:func:`omnirecon.engine.scenes.load_at_resolution`,
its probes) or a checkpoint loaded to the same device (:func:`omnirecon.engine.checkpoint.load_checkpoint`) is read
from disk once and served from memory after, as a copy each time: a stage may change what it gets (fine-tuning
changes the model's weights in place), and the next stage must get what the disk holds. Outside it every read reads.
"""

from __future__ import annotations

import copy
from collections import Counter
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Callable, TypeVar

T = TypeVar("T")

_STORE: ContextVar[dict | None] = ContextVar("omnirecon_held_reads", default=None)


@contextmanager
def holding(store: dict, reads: Counter | None = None):
    """Hold the reads made inside in ``store`` (a dict the caller keeps: what is held lives as long as it does);
    ``reads`` counts the reads from disk per kind (``scene``, ``scene_probe``, ``checkpoint``)."""
    token = _STORE.set({"values": store, "reads": reads if reads is not None else Counter()})
    try:
        yield store
    finally:
        _STORE.reset(token)


def held(kind: str, key: tuple, read: Callable[[], T]) -> T:
    """``read()``; while :func:`holding`, the value held under ``(kind, *key)``, read once, copied."""
    store = _STORE.get()
    if store is None:
        return read()
    key = (kind, *key)
    if key not in store["values"]:
        store["values"][key] = read()
        store["reads"][kind] += 1
    return copy.deepcopy(store["values"][key])
