"""Which views a command uses: the K sources nearest a target, the default sources of a scene, checks
of user-given view lists, and the held-out views a mesh is scored on."""

from __future__ import annotations

import numpy as np
from torch import Tensor

from omnirecon.cameras import closest_point_to_axes, nearest_views
from omnirecon.data.scene import Scene
from omnirecon.errors import InputError
from omnirecon.scene_kind import scene_kind

DTU_VIEWS = (23, 24, 33)
"""The sparse-view DTU setting of SparseNeuS / VolRecon / Omni-Recon (the first 3 of set 0)."""
DTU_FORMATS = ("dtu_neus", "dtu_mvsnet")
MAX_HELD_OUT = 8
"""Held-out views scored for silhouette IoU and depth (evenly spaced, like the DTU eval protocol)."""


def view_metric(scene: Scene) -> str:
    """``"angle"`` (around the look-at centre) for object rigs, ``"distance"`` otherwise."""
    return scene_kind(scene).rank_by


def select_sources(scene: Scene, camera, pool: list[int], k: int, center: Tensor | None = None) -> list[int]:
    """The ``k`` views of ``pool`` nearest to ``camera`` (one :class:`Cameras`), nearest first.

    Distance is the angle seen from ``center`` (default: the point closest to all optical axes)
    for object rigs, the distance between camera centres otherwise.
    """
    by = view_metric(scene)
    if by == "angle" and center is None:
        center = closest_point_to_axes(scene.cameras)
    cams = scene.cameras[pool]
    idx = nearest_views(camera.to(dtype=cams.c2w.dtype), cams, k, by=by,
                        center=None if center is None else center.to(cams.c2w))[0]
    return [pool[int(i)] for i in idx]


def default_views(scene, num_views: int) -> list[int]:
    """DTU's (23, 24, 33) for DTU scans of 49 views, else ``num_views`` evenly spaced train views."""
    if scene.format in DTU_FORMATS and len(scene) > max(DTU_VIEWS):
        return list(DTU_VIEWS)
    pool = scene.splits.get("train") or list(range(len(scene)))
    if num_views < 1 or num_views > len(pool):
        raise InputError(f"--num-views must be in 1..{len(pool)} (the train views), got {num_views}", scene.path,
                         "pass fewer views or name them with --views")
    pick = np.unique(np.linspace(0, len(pool) - 1, num_views).round().astype(int))
    return [pool[i] for i in pick]


def check_views(views, n: int, where, scene=None) -> list[int]:
    """``--views`` as indices: integers in ``0..n-1``, or ``all`` (the scene's train views, else every view)."""
    views = [str(v).strip() for v in views]
    if views == ["all"]:
        pool = (scene.splits.get("train") if scene is not None else None) or list(range(n))
        return list(pool)
    try:
        views = [int(v) for v in views]
    except ValueError:
        raise InputError(f"--views must be view indices or `all`, got {' '.join(views)}", where,
                         "pass e.g. --views 0 8 17 or --views all") from None
    bad = [v for v in views if not 0 <= v < n]
    if bad or not views:
        raise InputError(f"--views must name views in 0..{n - 1}, got {views}", where,
                         "list view indices as printed by `omnirecon inspect`")
    if len(set(views)) != len(views):
        raise InputError(f"--views repeats a view: {views}", where, "name each view once")
    return views


def held_out_views(scene, sources: list[int], cap: int = MAX_HELD_OUT) -> list[int]:
    """Views to score: the test split (else every view) minus the sources, at most ``cap`` evenly spaced."""
    cand = [i for i in (scene.splits.get("test") or range(len(scene))) if i not in set(sources)]
    if len(cand) > cap:
        cand = [cand[i] for i in np.unique(np.linspace(0, len(cand) - 1, cap).round().astype(int))]
    return cand
