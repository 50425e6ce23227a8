"""Reads a run holds (omnirecon/engine/held.py): inside ``holding`` a scene or checkpoint is read from disk once, and
each caller gets its own copy (a stage that changes what it got changes nothing for the next)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import torch

from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.engine.checkpoint import load_checkpoint
from omnirecon.engine.held import holding
from omnirecon.engine.scenes import load_at_resolution, photo_side

CK = Path(__file__).resolve().parents[2] / "checkpoints" / "omnirecon-tiny"


def test_a_held_scene_is_read_once_and_copied(tmp_path):
    path = generate_scene(tmp_path / "s", 0, SynthOptions(rig="frontal", views=4, resolution=32))
    store, reads = {}, Counter()
    with holding(store, reads):
        a = load_at_resolution(path, 24)
        a.images.mul_(0)  # a stage changing what it got
        b = load_at_resolution(path, 24)
        photo_side(path)
        load_at_resolution(path, 16)
    assert reads == Counter({"scene": 2, "scene_probe": 1}), reads  # 24 and 16 px; one probe for every size
    fresh = load_at_resolution(path, 24)  # outside: read again
    assert torch.equal(b.images, fresh.images) and b.images.abs().sum() > 0
    assert len(store) == 3  # what the caller keeps holds every read


def test_a_held_checkpoint_is_loaded_once_and_copied():
    store, reads = {}, Counter()
    with holding(store, reads):
        m1, _ = load_checkpoint(CK)
        with torch.no_grad():
            for p in m1.parameters():
                p.zero_()  # fine-tuning changes the weights in place
        m2, _ = load_checkpoint(CK)
    assert reads == Counter({"checkpoint": 1})
    fresh, _ = load_checkpoint(CK)
    assert all(torch.equal(a, b) for a, b in zip(m2.state_dict().values(), fresh.state_dict().values()))
