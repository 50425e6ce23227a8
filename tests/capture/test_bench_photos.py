"""bench poses --photos: a walk's breaks and the agreement of two pose sets, per piece between breaks."""

import numpy as np
from scipy.spatial.transform import Rotation

from bench.poses_photos import agreement, breaks


def walk(n: int) -> np.ndarray:
    """``n`` cameras ``# [n, 4, 4]`` one unit apart along x, turning 2 degrees per step."""
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, :3, :3] = Rotation.from_euler("y", 2 * np.arange(n)[:, None], degrees=True).as_matrix()
    c2w[:, 0, 3] = np.arange(n)
    return c2w


def test_breaks_and_pieces():
    """A walk whose second half was put 50 steps away and turned 90 degrees is broken there; the other walk is not,
    so they disagree as wholes and agree on each piece."""
    good = walk(12)
    broken = good.copy()
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    turn[:3, 3] = [0, 50, 0]
    broken[6:] = turn @ good[6:]
    assert breaks(good) == [] and breaks(broken) == [6]
    whole = agreement(good, broken)
    assert whole["centre_pct_median"] > 5 and whole["rotation_deg_max"] > 10
    for a, b in ((0, 6), (6, 12)):
        piece = agreement(good[a:b], broken[a:b])
        assert piece["centre_pct_max"] < 1e-6 and piece["rotation_deg_max"] < 1e-3
