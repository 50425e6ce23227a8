"""Is there one rigid scene? A turntable check on the matches and the poses structure from motion found.

Structure from motion assumes one rigid scene. When an object turns on a stand while the camera and the room
stay still (ethiopianHead: a bronze head on a turntable), the photos hold two motions: the object turns, the
room does not move in the image at all (or moves as a whole, when the photos were cropped). The mapper poses
the cameras from a mix, so no single rigid scene fits the photos (held-out views score low, and part of them is
not covered).

The check (:func:`still_background`): for image pairs whose poses differ by at least :data:`MIN_TURN` degrees of
rotation, the share of their matches that move by one and the same image offset (within :data:`SAME_PX` px). A
camera that turned that far sees every point of a rigid scene move by an offset that changes across the image
(with depth and position); a still background moves as one piece. On ethiopianHead half of the matches of such
pairs move as one piece; the capture scores as a turntable when the median share passes :data:`STILL`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

MIN_TURN = 10.0
"""Degrees of rotation between two posed photos for their pair to count."""
SAME_PX = 2.0
"""Two matches move by the same offset when their offsets differ by less than this many pixels."""
STILL = 0.25
"""Median share of a pair's matches moving as one piece above which the capture is a turntable."""
MAX_PAIRS = 60
"""Pairs looked at (the ones with the most matches), and at most 400 matches of each: a fraction of a second."""


def common_offset_share(xa: np.ndarray, xb: np.ndarray, same_px: float = SAME_PX, max_matches: int = 400,
                        seed: int = 0) -> float:
    """The largest share of the matches ``xa[i] -> xb[i]`` (pixel positions ``# [R, 2]`` each) whose image offsets
    ``xb - xa`` lie within ``same_px`` of one match's offset (at most ``max_matches`` of them, a fixed sample)."""
    disp = np.asarray(xb, np.float64) - np.asarray(xa, np.float64)  # [R, 2]
    if len(disp) > max_matches:
        disp = disp[np.random.default_rng(seed).choice(len(disp), max_matches, replace=False)]
    if len(disp) == 0:
        return 0.0
    near = np.linalg.norm(disp[:, None] - disp[None], axis=-1) < same_px  # [R, R]
    return float(near.sum(1).max() / len(disp))


def still_background(db: Path, reconstruction, min_matches: int = 30) -> dict:
    """The turntable score of COLMAP database ``db`` and the ``reconstruction`` (pycolmap) mapped from it: over the
    (up to :data:`MAX_PAIRS`) registered pairs turned at least :data:`MIN_TURN` degrees apart with ``min_matches``
    or more raw matches, the median :func:`common_offset_share`. Returns ``{"pairs", "share", "turntable"}``
    (``share`` None and ``turntable`` False when no pair qualifies: a capture whose photos all face one way)."""
    import pycolmap  # lazy: the optional 'capture' extra

    rot = {}
    for im in (reconstruction.images[i] for i in reconstruction.reg_image_ids()):  # the pose check de-registers some
        pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        rot[im.name] = np.asarray(pose.rotation.matrix())
    shares = []
    with pycolmap.Database.open(db) as d:
        names = {im.image_id: im.name for im in d.read_all_images()}
        pair_ids, geoms = d.read_two_view_geometries()
        ranked = sorted(zip(pair_ids, geoms), key=lambda pg: -len(pg[1].inlier_matches))
        for pid, _ in ranked:
            a, b = pycolmap.pair_id_to_image_pair(int(pid))
            if names.get(a) not in rot or names.get(b) not in rot:
                continue
            R = rot[names[a]] @ rot[names[b]].T
            turn = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))
            if turn < MIN_TURN:
                continue
            raw = d.read_matches(a, b).astype(np.int64)  # [R, 2] every match, verified or not
            if len(raw) < min_matches:
                continue
            ka, kb = d.read_keypoints(a)[:, :2], d.read_keypoints(b)[:, :2]
            shares.append(common_offset_share(ka[raw[:, 0]], kb[raw[:, 1]]))
            if len(shares) == MAX_PAIRS:
                break
    share = float(np.median(shares)) if shares else None
    return {"pairs": len(shares), "share": None if share is None else round(share, 3), "min_turn": MIN_TURN,
            "turntable": share is not None and share >= STILL}
