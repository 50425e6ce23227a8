"""A sensible scene frame for poses in an arbitrary frame (COLMAP output): up, centre and scale.

Structure from motion returns poses in whatever frame its first image pair defined: any rotation,
any scale. :func:`upright_frame` picks the similarity ``T`` (scene frame <- input frame) that makes

* **up** the +z axis. People (and robot arms, and Blender's look-at) hold cameras level: the right
  axis (``x``) of every camera is horizontal whatever its pitch. When the right axes spread in yaw,
  up is the normal of the plane they span (signed like the cameras' mean up vector, ``-y``);
  when they are all parallel (a forward-facing rig) up is the mean of the cameras' up vectors;
* **yaw** such that the cameras' mean viewing direction, made horizontal, is +y;
* **centre and scale** such that the robust box of the 3-D points (per-axis 1st to 99th percentile,
  in the upright frame) is centred at 0 and its half-diagonal is 1.

Readers apply ``T`` to cameras, points and depth bounds and store ``to_input = T^-1``
(:class:`~omnirecon.data.scene.Scene`), so exports land back in the input frame.
"""

from __future__ import annotations

import numpy as np

PCT = (1.0, 99.0)
SPREAD = 0.03
"""Second eigenvalue of the right axes' scatter above which they span a plane (yaw spread > ~10 degrees)."""


def up_vector(c2w: np.ndarray) -> np.ndarray:
    """Unit up direction of cameras ``c2w # [N, 4, 4]`` (OpenCV), in their frame (see the module docstring)."""
    up = -c2w[:, :3, 1].mean(0)
    up /= max(np.linalg.norm(up), 1e-12)
    x = c2w[:, :3, 0]  # [N, 3] camera right axes: horizontal when the camera is held level
    evals, evecs = np.linalg.eigh(x.T @ x / len(x))  # ascending
    if evals[1] > SPREAD:  # the right axes span a plane: up is its normal, whatever the cameras' pitch
        normal = evecs[:, 0]
        return normal if normal @ up >= 0 else -normal
    return up


def rotation_to_up(c2w: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Rotation ``# [3, 3]`` (new <- old) sending ``up`` to +z and the horizontal mean view direction to +y."""
    fwd = c2w[:, :3, 2].mean(0)
    fwd = fwd - (fwd @ up) * up
    if np.linalg.norm(fwd) < 1e-6:  # cameras looking straight up/down on average: use the first x axis
        x = c2w[0, :3, 0] - (c2w[0, :3, 0] @ up) * up
        fwd = np.cross(up, x)
    y = fwd / np.linalg.norm(fwd)
    x = np.cross(y, up)
    return np.stack([x, y, up])


def upright_frame(c2w: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(T, bounds)``: the similarity ``T # [4, 4]`` (scene <- input) of the module docstring and the
    robust box of ``points # [P, 3]`` in the scene frame, ``bounds # [2, 3]``."""
    c2w, points = np.asarray(c2w, np.float64), np.asarray(points, np.float64)
    R = rotation_to_up(c2w, up_vector(c2w))
    p = points @ R.T
    lo, hi = np.percentile(p, PCT, axis=0)
    centre = (lo + hi) / 2
    s = 1.0 / max(np.linalg.norm(hi - lo) / 2, 1e-12)
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = -s * centre
    return T, np.stack([(lo - centre) * s, (hi - centre) * s])
