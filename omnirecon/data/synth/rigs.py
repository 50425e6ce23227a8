"""Camera rigs: where the cameras of a procedural scene stand and where they look.

All rigs return OpenCV camera-to-world matrices (``omnirecon.cameras.look_at``) in a z-up world.

* ``object``: cameras spread evenly over a band of elevations on a sphere around the content,
  looking at its centre (NeRF-synthetic-like 360 degree captures).
* ``frontal``: cameras on an arc of +-40 degrees azimuth in a few rows of elevation, at similar
  distances, all facing the object (DTU-like).
* ``forward``: cameras on a small vertical grid, all looking the same way into a layered scene
  (LLFF-like forward-facing captures).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from omnirecon.cameras import look_at

UP = np.array([0.0, 0.0, 1.0])
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def fit_distance(radius: float, fov: float, margin: float = 1.1) -> float:
    """Camera distance at which a sphere of ``radius`` fits inside a view of angle ``fov`` (radians).

    A sphere at distance ``d`` subtends a cone of half-angle ``asin(radius / d)``; ``margin`` > 1
    leaves a border.
    """
    return margin * radius / math.sin(fov / 2)


def _look_at(eyes: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """OpenCV c2w for cameras at ``eyes # [N, 3]`` looking at ``targets # [N, 3]``, z up. ``# [N, 4, 4]``"""
    c2w = look_at(torch.tensor(np.asarray(eyes, dtype=np.float64)),
                  torch.tensor(np.asarray(targets, dtype=np.float64)), torch.tensor(UP))
    return c2w.numpy()


def sphere_band(centre: np.ndarray, distance: float, views: int, elevation: tuple[float, float],
                rng: np.random.Generator) -> np.ndarray:
    """``object`` rig: a Fibonacci spiral over the elevation band (degrees), evenly covering it. ``# [V, 4, 4]``"""
    lo, hi = np.sin(np.radians(elevation))
    z = lo + (np.arange(views) + 0.5) / views * (hi - lo)  # uniform in z = uniform in area
    azimuth = rng.uniform(0, 2 * np.pi) + GOLDEN_ANGLE * np.arange(views)
    r = np.sqrt(1 - z**2)
    dirs = np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], axis=1)
    eyes = centre + distance * dirs
    return _look_at(eyes, np.broadcast_to(centre, eyes.shape))


def frontal_arc(centre: np.ndarray, distance: float, views: int, rng: np.random.Generator,
                azimuth_range: float = 40.0, elevation: tuple[float, float] = (10.0, 45.0)) -> np.ndarray:
    """``frontal`` rig: rows of cameras on an arc of ``+-azimuth_range`` degrees facing ``centre``.

    Rows run from low to high elevation in a serpentine order, so consecutive views are
    neighbours; distances vary by up to 10 % (never closer than ``distance``). ``# [V, 4, 4]``
    """
    rows = max(1, round(math.sqrt(views / 2)))
    per_row = np.full(rows, views // rows) + (np.arange(rows) < views % rows)
    facing = rng.uniform(0, 2 * np.pi)
    eyes = []
    for r, n in enumerate(per_row):
        el = np.radians(np.interp((r + 0.5) / rows, [0, 1], elevation) + rng.uniform(-2, 2))
        az = np.radians(np.linspace(-azimuth_range, azimuth_range, n) if n > 1 else np.zeros(1))
        az = az + np.radians(rng.uniform(-2, 2, n))
        az = az if r % 2 == 0 else az[::-1]
        d = distance * rng.uniform(1.0, 1.1, n)
        eyes.append(np.stack([d * np.cos(el) * np.cos(facing + az), d * np.cos(el) * np.sin(facing + az),
                              d * np.sin(el) * np.ones(n)], axis=1))
    eyes = centre + np.concatenate(eyes)
    return _look_at(eyes, np.broadcast_to(centre, eyes.shape))


def forward_grid(origin: np.ndarray, direction: np.ndarray, views: int, extent: float,
                 rng: np.random.Generator) -> np.ndarray:
    """``forward`` rig: a jittered grid of parallel cameras on the plane through ``origin``.

    The grid spans ``+-extent`` sideways and ``+-0.6 extent`` vertically (in the camera's image
    plane) and is filled row by row, serpentine. ``# [V, 4, 4]``
    """
    cols = math.ceil(math.sqrt(views * 1.5))
    rows = math.ceil(views / cols)
    base = _look_at(origin[None], (origin + direction)[None])[0]
    right, down = base[:3, 0], base[:3, 1]
    eyes = []
    for i in range(views):
        r, c = divmod(i, cols)
        c = c if r % 2 == 0 else cols - 1 - c
        x = (c / max(cols - 1, 1) * 2 - 1) * extent + rng.uniform(-0.1, 0.1) * extent / cols
        y = ((r / max(rows - 1, 1) * 2 - 1) if rows > 1 else 0.0) * 0.6 * extent
        eyes.append(origin + x * right + y * down)
    eyes = np.stack(eyes)
    return _look_at(eyes, eyes + direction)


def intrinsics(fov: float, width: int, height: int) -> np.ndarray:
    """Pinhole ``K # [3, 3]`` with horizontal field of view ``fov`` (radians), square pixels, centred."""
    f = width / 2 / math.tan(fov / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
