"""Which data may be trained on and which is reserved for evaluation (see docs/evaluation.md)."""

import numpy as np

TRAIN_SEEDS = range(0, 900_000)
"""Procedural scene seeds that training may draw from."""
EVAL_SEEDS = range(900_000, 901_000)
"""Procedural scene seeds reserved for evaluation; training refuses them."""
VAL_SEEDS = range(901_000, 902_000)
"""Procedural scene seeds for validation during training (``synth:RIG:N`` in ``--val-scenes``):
neither trained on nor part of the evaluation sets, so monitoring never looks at test scenes."""
EVAL_ONLY_SCENES = ("dtu_scan24", "dtu_scan37", "fern")
"""Real scenes that are never trained on (folder names)."""

DTU_SOURCES = (23, 24, 33)
"""The sparse-view DTU sources of SparseNeuS / VolRecon / Omni-Recon (the first 3 of set 0)."""
DTU_HELD_OUT = 8
"""Held-out views of a DTU scan (the DTU evaluation protocol's target cap)."""


def dtu_held_out(n: int, cap: int = DTU_HELD_OUT) -> list[int]:
    """The DTU protocol's held-out views of an ``n``-view scan: ``cap`` views evenly spaced over the
    views other than :data:`DTU_SOURCES` (``engine/protocols.py`` picks the same ones). The readers
    give them as the scan's ``test`` split, so no mesh, tuning set or source set sees them."""
    candidates = [i for i in range(n) if i not in DTU_SOURCES]
    if len(candidates) <= cap:
        return candidates
    pick = np.unique(np.linspace(0, len(candidates) - 1, cap).round().astype(int))
    return [candidates[i] for i in pick]
