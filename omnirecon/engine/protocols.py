"""The evaluation protocols: one fixed rule per dataset for which views are targets, which form the
source pool, at what resolution and background, with which masks and crops (``docs/evaluation.md``
has the same table in words)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from omnirecon.data.io import read_json
from omnirecon.data.scene import Scene
from omnirecon.errors import InputError
from omnirecon.scene_kind import scene_kind

SYNTH_PREFIX = "synth:eval"
"""Scene spec of the held-out procedural set (``synth:eval`` or ``synth:eval:<rig>``)."""


@dataclass(frozen=True)
class Protocol:
    """How one dataset is evaluated. Every field is part of the published protocol."""

    name: str
    """Protocol key, used in result tables."""
    datasets: str
    """Which scenes it applies to."""
    rule: Literal["test_split", "every_8th", "dtu"]
    """Target/pool rule: the reader's test split vs train split; every 8th view vs the rest; DTU's
    targets = views other than the 3 fixed sources, pool = every non-target view."""
    max_targets: int | None = None
    """Cap on target views (picked by ``pick``), for CPU cost."""
    pick: Literal["first", "even"] = "first"
    """How the cap picks targets: the first ones, or evenly spaced over the candidates."""
    fixed_sources: tuple[tuple[int, tuple[int, ...]], ...] = ()
    """``(K, views)`` pairs: for these K every target uses exactly these source views."""
    long_side: int = 128
    """Images are area-downscaled so the long side is at most this many pixels (never upscaled)."""
    background: Literal["white", "black"] = "white"
    """Colour RGBA inputs are composited on (for sources and ground truth alike)."""
    masked: bool = False
    """Also report ``psnr_masked``: PSNR over the foreground-mask pixels of the ground truth."""
    crop: float = 0.0
    """Fraction of each border cropped before scoring (0 = the full image)."""
    split: Literal["protocol", "extrapolation"] = "protocol"
    """``protocol``: targets and pool by ``rule``; ``extrapolation``: the test views of :func:`extrapolation_split`
    are the targets and its training views the pool (views beyond those a user photographed)."""


PROTOCOLS: dict[str, Protocol] = {
    "blender": Protocol("blender", "Blender / NeRF-synthetic (lego, chair)", "test_split", max_targets=8,
                        pick="first", masked=True),
    "dtu": Protocol("dtu", "DTU (NeuS or MVSNet layout; dtu_scan24, dtu_scan37)", "dtu", max_targets=8, pick="even",
                    fixed_sources=((3, (23, 24, 33)),), masked=True),
    "llff": Protocol("llff", "LLFF poses_bounds.npy captures (fern; ethiopianHead)", "every_8th"),
    "ngp": Protocol("ngp", "instant-ngp transforms.json captures (fox)", "every_8th"),
    "colmap": Protocol("colmap", "COLMAP sparse models", "every_8th"),
    "synth": Protocol("synth", "omnirecon procedural scenes (synth:eval, seeds 900000+)", "test_split"),
}
"""The one protocol per dataset; ``docs/evaluation.md`` has the same table in words."""

CPU_TARGETS = {"blender": 3, "dtu": 4, "llff": 3, "ngp": 3, "colmap": 3, "synth": 2}
"""Targets per scene of the ``cpu`` protocol set (evenly spaced over the full protocol's candidates)."""
CPU256_TARGETS = 2
"""Targets per scene of the ``cpu256`` and ``cpu256-extrapolation`` sets (evenly spaced), for CPU cost: BENCHMARKS
"Novel-view quality" gives the CPU-seconds of one 256-px view per model."""
CPU256 = {k: replace(p, long_side=256, max_targets=CPU256_TARGETS, pick="even") for k, p in PROTOCOLS.items()}
PROTOCOL_SETS: dict[str, dict[str, Protocol]] = {
    "full": PROTOCOLS,
    "cpu": {k: replace(p, long_side=64, max_targets=CPU_TARGETS[k], pick="even") for k, p in PROTOCOLS.items()},
    "cpu256": CPU256,
    "cpu256-extrapolation": {k: replace(p, split="extrapolation", fixed_sources=()) for k, p in CPU256.items()},
}
"""``full``: the published protocols. ``cpu``: the same rules at a 64-px long side (the tiny presets'
training resolution) with fewer targets, so a CPU can score GPNR and IBRNet in minutes. ``cpu256``: the same rules
at a 256-px long side (near the size users look at) with :data:`CPU256_TARGETS` targets. ``cpu256-extrapolation``:
``cpu256`` with the extrapolation split's test views as targets and its training views as the pool (no fixed
sources). Numbers are labelled with the set's name and are not comparable across sets."""


def set_long_side(protocol_set: str) -> int:
    """The long side (px) the protocols of ``protocol_set`` score at (the largest where they differ): the size a
    checkpoint's weights are chosen for (``omnirecon.engine.checkpoint.folder_for_size``)."""
    return max(p.long_side for p in PROTOCOL_SETS[protocol_set].values())


FORMAT_PROTOCOL = {"blender": "blender", "ngp": "ngp", "llff": "llff", "dtu_neus": "dtu", "dtu_mvsnet": "dtu",
                   "colmap": "colmap"}
"""Reader name -> protocol (a Blender-layout folder written by ``omnirecon synth`` uses ``synth``)."""

SYNTH_VIEWS = 40
"""Views per held-out procedural scene (5 test targets, 30 train views in the pool)."""


def is_synth(path: Path) -> bool:
    """``path`` holds a scene written by ``omnirecon synth`` (its ``scene.json`` names the generator)."""
    meta = Path(path) / "scene.json"
    if not meta.is_file():
        return False
    return str(read_json(meta).get("generator_version", "")).startswith("omnirecon-synth")


def protocol_for(path: Path, fmt: str, protocol_set: str = "full") -> Protocol:
    """The protocol of the scene at ``path`` read by reader ``fmt``, from set ``protocol_set``."""
    table = PROTOCOL_SETS[protocol_set]
    if fmt == "blender" and path is not None and is_synth(path):
        return table["synth"]
    return table[FORMAT_PROTOCOL[fmt]]


def targets_and_pool(protocol: Protocol, scene: Scene, max_targets: int | None = None) -> tuple[list[int], list[int]]:
    """Target views and the source pool of ``scene`` under ``protocol`` (disjoint, sorted).

    ``max_targets`` overrides the protocol's cap (results then say they are not the protocol's).
    """
    n = len(scene)
    cap = protocol.max_targets if max_targets is None else max_targets
    if protocol.split == "extrapolation":
        split = extrapolation_split(scene)
        candidates, pool_from = split.test, split.train
    elif protocol.rule == "test_split":
        test = scene.splits.get("test", [])
        if not test:
            raise InputError("scene has no test split", scene.path, f"the {protocol.name} protocol scores the "
                             "test split; give a scene with transforms_test.json")
        candidates = sorted(test)
        pool_from = sorted(scene.splits.get("train") or [i for i in range(n) if i not in set(test)])
    elif protocol.rule == "every_8th":
        candidates = list(range(0, n, 8))
        pool_from = [i for i in range(n) if i % 8]
    else:  # dtu
        fixed = dict(protocol.fixed_sources)[3]
        if n <= max(fixed):
            raise InputError(f"DTU protocol needs views {fixed} but the scene has {n} views", scene.path,
                             "give the full 49-view DTU scan")
        candidates = [i for i in range(n) if i not in fixed]
        pool_from = None
    if cap is not None and len(candidates) > cap:
        if protocol.pick == "first":
            candidates = candidates[:cap]
        else:
            pick = np.unique(np.linspace(0, len(candidates) - 1, cap).round().astype(int))
            candidates = [candidates[i] for i in pick]
    targets = candidates
    pool = [i for i in range(n) if i not in set(targets)] if pool_from is None else pool_from
    pool = [i for i in pool if i not in set(targets)]
    return targets, pool


def given_targets(protocol: Protocol, scene: Scene, targets, num_views: int, path) -> tuple[list[int], list[int]]:
    """``(targets, source pool)``: the protocol's, or ``targets`` (a verb's ``--targets``) with every other view
    as the pool; refuses targets outside the scene and a pool of fewer than ``num_views`` views."""
    chosen, pool = targets_and_pool(protocol, scene)
    if targets:
        bad = [t for t in targets if not 0 <= t < len(scene)]
        if bad:
            raise InputError(f"--targets {bad} outside the scene's views 0..{len(scene) - 1}", path,
                             "pick view indices of the scene")
        chosen = list(targets)
        pool = [v for v in range(len(scene)) if v not in set(chosen)]
    if len(pool) < num_views:
        raise InputError(f"the source pool has {len(pool)} views, fewer than --num-views {num_views}", path,
                         "lower --num-views")
    return chosen, pool


EXTRAPOLATION_ARC = 100.0
"""Degrees of azimuth the training views of an extrapolation split cover, at most (a capture that covers less keeps
:data:`EXTRAPOLATION_MARGIN` degrees at each end of what it covers for the test views)."""
EXTRAPOLATION_BEYOND = (10.0, 30.0)
"""Test views of an extrapolation split lie this many degrees of azimuth beyond the training arc (nearest end)."""
EXTRAPOLATION_MARGIN = 20.0
"""Degrees left at each end of a partial capture's arc for the test views."""
WALK_HOLD = 0.15
"""Forward-facing captures (walks): the last this fraction of the views, in capture order, are the test views."""


@dataclass(frozen=True)
class ExtrapolationSplit:
    """Training views a user might have photographed and test views just beyond them (``docs/evaluation.md``)."""

    train: list[int]
    """The views meshed and blended: those within one arc of azimuth (object rigs) or the first stretch of a walk."""
    test: list[int]
    """Views beyond the training views, never among them."""
    kind: Literal["arc", "walk"]
    """``arc``: azimuth around the point closest to the optical axes; ``walk``: the capture order."""
    beyond: list[float]
    """Per test view: degrees of azimuth beyond the arc's nearest end (``arc``), or views past the last training
    view in capture order (``walk``)."""
    arc: float | None = None
    """Degrees of azimuth the training views span (``arc``)."""


def extrapolation_split(scene: Scene, pool: list[int] | None = None, arc: float = EXTRAPOLATION_ARC,
                        beyond: tuple[float, float] = EXTRAPOLATION_BEYOND) -> ExtrapolationSplit:
    """The extrapolation split of ``scene``'s views ``pool`` (default: every view).

    Object rigs: azimuths about the cameras' mean up around the point closest to their optical axes. A capture
    that goes around takes the ``arc`` degrees starting at the first view of ``pool``; one that covers a partial arc
    of ``S`` degrees takes ``min(arc, S - 2 x 20)`` degrees centred in it. Test views lie ``beyond`` degrees past
    either end. Forward-facing rigs (LLFF grids) and walks (:func:`omnirecon.trajectory.is_walk`, whatever the rig):
    the last :data:`WALK_HOLD` of ``pool`` (at least 2 views)
    are the test views. Raises :class:`InputError` when no test view or fewer than 2 training views result.
    """
    import math

    import torch

    from omnirecon.cameras import closest_point_to_axes
    from omnirecon.trajectory import azimuth_frame, azimuths, captured_arc, is_walk

    pool = sorted(pool) if pool is not None else list(range(len(scene)))
    if scene_kind(scene).forward or is_walk(scene.cameras[pool]):
        n_test = max(2, round(WALK_HOLD * len(pool)))
        train, test = pool[:-n_test], pool[-n_test:]
        split = ExtrapolationSplit(train, test, "walk", [float(k + 1) for k in range(n_test)])
    else:
        cams = scene.cameras[pool].to(dtype=torch.float64)
        center = closest_point_to_axes(cams)
        az = torch.rad2deg(azimuths(cams, center))  # [P], view pool[0] at 0
        up, e1, e2 = azimuth_frame(cams, center)
        start, span = captured_arc(cams.centers - center, up, e1, e2)
        start, span = math.degrees(start), math.degrees(span)
        width = arc if span >= 360 else min(arc, span - 2 * EXTRAPOLATION_MARGIN)
        lo = 0.0 if span >= 360 else start + (span - width) / 2
        rel = (az - lo).remainder(360)  # [P] degrees past the arc's start
        past = torch.minimum((rel - width).clamp_min(0), (360 - rel).remainder(360))  # beyond the nearest end
        past = torch.where(rel <= width, torch.zeros_like(past), past)
        train = [v for v, r in zip(pool, rel.tolist()) if r <= width]
        pick = [(v, p) for v, p in zip(pool, past.tolist()) if beyond[0] <= p <= beyond[1]]
        split = ExtrapolationSplit(train, [v for v, _ in pick], "arc", [round(p, 1) for _, p in pick], width)
    if len(split.train) < 2 or not split.test:
        raise InputError(f"no extrapolation split: {len(split.train)} training and {len(split.test)} test views",
                         scene.path, "give a capture with more views around the object (or along the walk)")
    return split
