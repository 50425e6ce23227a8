"""Which data may be trained on and which is reserved for evaluation (see docs/evaluation.md)."""

TRAIN_SEEDS = range(0, 900_000)
"""Procedural scene seeds that training may draw from."""
EVAL_SEEDS = range(900_000, 901_000)
"""Procedural scene seeds reserved for evaluation; training refuses them."""
EVAL_ONLY_SCENES = ("dtu_scan24", "dtu_scan37", "fern")
"""Real scenes that are never trained on (folder names)."""
