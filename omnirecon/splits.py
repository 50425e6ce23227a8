"""Which data may be trained on and which is reserved for evaluation (see docs/evaluation.md)."""

TRAIN_SEEDS = range(0, 900_000)
"""Procedural scene seeds that training may draw from."""
EVAL_SEEDS = range(900_000, 901_000)
"""Procedural scene seeds reserved for evaluation; training refuses them."""
VAL_SEEDS = range(901_000, 902_000)
"""Procedural scene seeds for validation during training (``synth:RIG:N`` in ``--val-scenes``):
neither trained on nor part of the evaluation sets, so monitoring never looks at test scenes."""
EVAL_ONLY_SCENES = ("dtu_scan24", "dtu_scan37", "fern")
"""Real scenes that are never trained on (folder names)."""
