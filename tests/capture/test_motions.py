"""The turntable check: a still background moves in the image as one piece; a rigid scene seen by a camera that
turned does not."""

import numpy as np

from omnirecon.capture.motions import STILL, common_offset_share
from omnirecon.capture.process import motion_lines


def project(points: np.ndarray, R: np.ndarray, t: np.ndarray, f: float = 300.0, c: float = 200.0) -> np.ndarray:
    p = points @ R.T + t
    return f * p[:, :2] / p[:, 2:] + c


def turn(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def test_a_still_background_moves_as_one_piece_and_a_turned_camera_does_not():
    rng = np.random.default_rng(0)
    obj = rng.uniform(-0.6, 0.6, (200, 3))  # an object at the centre, 4 units away
    centre = np.array([0.0, 0.0, 4.0])
    room = rng.uniform([-4, -3, 6], [4, 3, 10], (200, 3))
    # a camera walking 15 degrees around the object: every offset differs (depth, position)
    orbit_t = centre - turn(15.0) @ centre
    xa = project(np.concatenate([obj + centre, room]), np.eye(3), np.zeros(3))
    xb = project(np.concatenate([obj + centre, room]), turn(15.0), orbit_t)
    walked = common_offset_share(xa, xb)
    # the camera stays, the object turns 15 degrees, the photo is cropped 7 px further right: the room moves as one
    xb_turntable = np.concatenate([project(obj @ turn(15.0).T + centre, np.eye(3), np.zeros(3)),
                                   project(room, np.eye(3), np.zeros(3))]) - np.array([7.0, 0.0])
    still = common_offset_share(xa, xb_turntable)
    assert walked < 0.2 < STILL < 0.45 < still
    assert common_offset_share(np.zeros((0, 2)), np.zeros((0, 2))) == 0.0


def test_the_hint_is_printed_for_a_turntable_without_masks_only():
    found = {"motions": {"turntable": True, "share": 0.52, "pairs": 60, "min_turn": 10.0}, "masks": None}
    (line,) = motion_lines(found)
    assert "--masks" in line and "52%" in line
    assert motion_lines({**found, "masks": "masks/"}) == []
    assert motion_lines({"motions": {**found["motions"], "turntable": False}}) == []
    assert motion_lines({"motions": None}) == [] and motion_lines({}) == []  # no pair qualified; an older summary
