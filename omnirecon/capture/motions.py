"""Is there one rigid scene? A turntable check on the matches structure from motion verified.

Structure from motion assumes one rigid scene. When an object turns on a stand in front of a still room
(ethiopianHead: a bronze head on a turntable), the photos hold two rigid motions: the room's and the object's.
COLMAP's two-view verification keeps the matches of the larger one per pair and the mapper then poses the
cameras from a mix, so no single rigid scene fits the photos (held-out 19.97 dB, coverage 87 %).

The check (:func:`second_motion`): per image pair, the matches that COLMAP's verification rejected are fitted
again with a fundamental matrix (OpenCV's RANSAC). Mismatches are scattered and few of them agree on one
epipolar geometry; the features of a second rigid body do. The ratio of those second-motion inliers to the
first motion's inliers, the median over the pairs with the most matches, is the score; a capture scores as
two-motion when it passes :data:`TWO_MOTIONS`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

TWO_MOTIONS = 0.25
"""Median ratio of second-motion to first-motion inliers above which a capture holds two rigid motions."""
MIN_SECOND = 30
"""Second-motion inliers a pair needs before it counts (fewer cannot be told from chance)."""


def second_motion(db: Path, pairs: int = 40, seed: int = 0, threshold_px: float = 1.5) -> dict:
    """The two-motion score of the matches in COLMAP database ``db`` (after matching and verification).

    Looks at the ``pairs`` image pairs with the most verified matches: the raw matches minus the verified ones
    (the ones the verification rejected) get a fundamental matrix by RANSAC (``threshold_px`` from the
    epipolar line); its inliers count as a second motion when there are at least :data:`MIN_SECOND`. Returns
    ``{"pairs", "first_inliers", "second_inliers", "ratio", "two_motions"}`` (medians over the pairs)."""
    import cv2
    import pycolmap  # lazy: the optional 'capture' extra

    cv2.setRNGSeed(int(seed))  # RANSAC's samples: the same score every run
    with pycolmap.Database.open(db) as d:
        pair_ids, geoms = d.read_two_view_geometries()
        ranked = sorted(zip(pair_ids, geoms), key=lambda pg: -len(pg[1].inlier_matches))[:pairs]
        firsts, seconds = [], []
        for pid, geom in ranked:
            a, b = pycolmap.pair_id_to_image_pair(int(pid))
            verified = geom.inlier_matches.astype(np.int64)  # [M, 2]
            n_in = len(verified)
            if n_in < 8:
                continue
            raw = d.read_matches(a, b).astype(np.int64)  # [R, 2]
            ka, kb = d.read_keypoints(a)[:, :2], d.read_keypoints(b)[:, :2]
            got = rejected_inliers(ka, kb, raw, verified, threshold_px)
            firsts.append(n_in)
            seconds.append(got if got >= MIN_SECOND else 0)
    if not firsts:
        return {"pairs": 0, "first_inliers": 0, "second_inliers": 0, "ratio": 0.0, "two_motions": False}
    ratio = float(np.median(np.array(seconds) / np.array(firsts)))
    return {"pairs": len(firsts), "first_inliers": int(np.median(firsts)), "second_inliers": int(np.median(seconds)),
            "ratio": round(ratio, 3), "two_motions": ratio >= TWO_MOTIONS}


def rejected_inliers(ka: np.ndarray, kb: np.ndarray, raw: np.ndarray, verified: np.ndarray,
                     threshold_px: float = 1.5) -> int:
    """How many of the matches ``raw # [R, 2]`` (keypoint indices into ``ka # [A, 2]``, ``kb # [B, 2]``, pixel
    positions) that are not in ``verified # [M, 2]`` share one epipolar geometry: the inliers of a fundamental
    matrix fitted to them by RANSAC (``threshold_px``), 0 with fewer than 8 such matches."""
    import cv2

    raw, verified = np.asarray(raw, np.int64).reshape(-1, 2), np.asarray(verified, np.int64).reshape(-1, 2)
    rest = raw[~np.isin(raw[:, 0] * (1 << 32) + raw[:, 1], verified[:, 0] * (1 << 32) + verified[:, 1])]
    if len(rest) < 8:
        return 0
    _, inl = cv2.findFundamentalMat(np.asarray(ka, np.float64)[rest[:, 0]], np.asarray(kb, np.float64)[rest[:, 1]],
                                    cv2.FM_RANSAC, threshold_px, 0.999, 2000)
    return int(inl.sum()) if inl is not None else 0
