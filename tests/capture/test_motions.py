"""The turntable check: matches that follow a second rigid motion, told apart from scattered mismatches."""

import numpy as np

from omnirecon.capture.motions import MIN_SECOND, rejected_inliers
from omnirecon.capture.process import motion_lines


def project(points: np.ndarray, R: np.ndarray, t: np.ndarray, f: float = 300.0, c: float = 200.0) -> np.ndarray:
    p = points @ R.T + t
    return f * p[:, :2] / p[:, 2:] + c


def turn(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def two_views(turntable: bool, n: int = 150, seed: int = 0):
    """Keypoints of two photos of a room (``n`` points, the camera moved) and, with ``turntable``, an object (``n``
    points at the centre) that turned 20 degrees between them while the camera stayed; else ``n`` mismatches.
    Returns keypoints of each photo, the raw matches and the verified ones (the room's)."""
    rng = np.random.default_rng(seed)
    room = rng.uniform([-4, -3, 6], [4, 3, 10], (n, 3))
    cam_b = (turn(4.0), np.array([0.4, 0.0, 0.0]))
    ka, kb = project(room, np.eye(3), np.zeros(3)), project(room, *cam_b)
    if turntable:
        obj = rng.uniform([-0.6, -0.6, -0.6], [0.6, 0.6, 0.6], (n, 3))
        centre = np.array([0.0, 0.0, 4.0])
        oa = project(obj + centre, np.eye(3), np.zeros(3))
        ob = project((obj @ turn(20.0).T + centre), *cam_b)
    else:
        oa, ob = rng.uniform(0, 400, (n, 2)), rng.uniform(0, 400, (n, 2))
    ka, kb = np.concatenate([ka, oa]), np.concatenate([kb, ob])
    raw = np.stack([np.arange(2 * n), np.arange(2 * n)], 1)
    return ka, kb, raw, raw[:n]


def test_a_second_rigid_motion_is_found_and_mismatches_are_not():
    ka, kb, raw, verified = two_views(turntable=True)
    assert rejected_inliers(ka, kb, raw, verified) >= 0.9 * 150
    ka, kb, raw, verified = two_views(turntable=False)
    assert rejected_inliers(ka, kb, raw, verified) < MIN_SECOND
    assert rejected_inliers(ka, kb, raw[:5], verified[:5]) == 0  # too few to fit


def test_the_hint_is_printed_for_two_motions_without_masks_only():
    two = {"motions": {"two_motions": True, "first_inliers": 300, "second_inliers": 120}, "masks": None}
    (line,) = motion_lines(two)
    assert "--masks" in line and "120" in line
    assert motion_lines({**two, "masks": "masks/"}) == []
    assert motion_lines({"motions": {**two["motions"], "two_motions": False}}) == []
    assert motion_lines({}) == []  # a summary written before the check existed
