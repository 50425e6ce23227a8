"""SIFT first, learned matches only where it fails: the views SIFT could not place and their neighbours.

After SIFT's mappings, :func:`learned_database` copies the COLMAP database and, for the images left
without a pose, chooses a few partners each (:func:`learned_pairs`: the next frames of a video, or for
photos the most similar posed and unposed images by visual words of their SIFT features,
:mod:`omnirecon.capture.retrieval`), never all pairs. The chosen images get learned keypoints (:mod:`omnirecon.capture.learned`) appended after
their SIFT keypoints, so every SIFT match keeps its indices; each chosen pair's LightGlue matches are
joined to its SIFT inliers and verified again with pycolmap (:func:`pycolmap.estimate_two_view_geometry`).
The caller maps that database like any other and keeps its model only under the retry rule
(:func:`omnirecon.capture.consistency.replaces`: more images, the same poses on the ones both have).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

NEIGHBOURS = 4
"""Partners per image SIFT could not place."""


def learned_pairs(db_path: Path, names: list[str], unplaced: list[str], video: bool,
                  k: int = NEIGHBOURS, seed: int = 0) -> list[tuple[int, int]]:
    """Index pairs ``(i, j)``, ``i < j`` of ``names``: each of ``unplaced`` with ``k`` partners, its nearest
    frames (``video``: ``k / 2`` on each side), or for photos its ``k`` most similar images among the posed
    ones (a group SIFT posed apart is most similar to itself: its own matches are not what it lacks), those
    ``k`` among themselves, and its ``k / 2`` most similar among the other unplaced ones."""
    index = {n: i for i, n in enumerate(names)}
    pairs = set()
    if video:
        for u in unplaced:
            i = index[u]
            for j in range(i - max(1, k // 2), i + max(1, k // 2) + 1):
                if j != i and 0 <= j < len(names):
                    pairs.add((min(i, j), max(i, j)))
        return sorted(pairs)
    from omnirecon.capture.retrieval import read_descriptors, word_histograms

    hist = word_histograms(read_descriptors(db_path, names), seed=seed)
    sim = hist @ hist.T  # [N, N]
    np.fill_diagonal(sim, -np.inf)
    away = np.zeros(len(names), bool)  # [N] without a pose
    away[[index[u] for u in unplaced]] = True
    for u in unplaced:
        i = index[u]
        chosen = {}
        for side, pool, count in (("posed", ~away, k), ("unposed", away, max(1, k // 2))):
            cand = np.flatnonzero(pool & np.isfinite(sim[i]))
            chosen[side] = [int(j) for j in cand[np.argsort(-sim[i, cand], kind="stable")[:count]]]
            pairs.update((min(i, j), max(i, j)) for j in chosen[side])
        posed = chosen["posed"]
        # the posed partners matched among themselves: their learned keypoints get 3-D points, through which
        # the mapper registers the unplaced view (it poses a view from 2-D to 3-D matches only)
        pairs.update((a, b) for a in posed for b in posed if a < b)
    return sorted(pairs)


def _append_keypoints(db, image_id: int, xy: np.ndarray) -> int:
    """Append ``xy`` [N, 2] to the image's keypoints (unit scale, no rotation); returns the former count."""
    kp = np.asarray(db.read_keypoints(image_id), np.float32)  # [K, C]: x, y (+ scale, orientation or affine)
    extra = np.zeros((len(xy), kp.shape[1]), np.float32)
    extra[:, :2] = xy
    if kp.shape[1] == 6:
        extra[:, 2] = extra[:, 5] = 1.0  # affine shape: identity
    elif kp.shape[1] == 4:
        extra[:, 2] = 1.0  # scale 1, orientation 0
    db.update_keypoints(image_id, np.concatenate([kp, extra]))
    return len(kp)


def learned_database(db_src: Path, db_out: Path, image_dir: Path, names: list[str], pairs: list[tuple[int, int]],
                     matcher, stages, seed: int = 0) -> dict:
    """A copy of ``db_src`` at ``db_out`` whose ``pairs`` (indices into ``names``) also hold learned matches
    (see the module's note). ``matcher``: a :class:`omnirecon.capture.learned.LearnedMatcher`. Returns
    what was done: images given learned features, pairs matched, matches added, verified pairs."""
    import pycolmap  # lazy: the optional 'capture' extra

    shutil.copyfile(db_src, db_out)
    involved = sorted({names[i] for p in pairs for i in p})
    feats = {}
    with stages.stage("features (learned)", len(involved)) as advance:
        for n in involved:
            feats[n] = matcher.features(image_dir / n)
            advance()
    added, verified = 0, 0
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.random_seed = seed
    with pycolmap.Database.open(str(db_out)) as db, stages.stage("matching (learned)", len(pairs)) as advance:
        ids = {im.name: im for im in db.read_all_images()}
        cams = {c.camera_id: c for c in db.read_all_cameras()}
        offset = {n: _append_keypoints(db, ids[n].image_id, feats[n].keypoints) for n in involved}
        for i, j in pairs:
            a, b = ids[names[i]], ids[names[j]]
            m = matcher.match(feats[a.name], feats[b.name]).astype(np.int64) + [offset[a.name], offset[b.name]]
            old = np.zeros((0, 2), np.int64)
            if db.exists_two_view_geometry(a.image_id, b.image_id):
                old = np.asarray(db.read_two_view_geometry(a.image_id, b.image_id).inlier_matches, np.int64)
                db.delete_two_view_geometry(a.image_id, b.image_id)
            if db.exists_matches(a.image_id, b.image_id):
                db.delete_matches(a.image_id, b.image_id)
            both = np.unique(np.concatenate([old.reshape(-1, 2), m]), axis=0).astype(np.uint32)  # [M, 2]
            ka = np.asarray(db.read_keypoints(a.image_id), np.float64)[:, :2]
            kb = np.asarray(db.read_keypoints(b.image_id), np.float64)[:, :2]
            g = pycolmap.estimate_two_view_geometry(cams[a.camera_id], ka, cams[b.camera_id], kb, both, verify)
            db.write_matches(a.image_id, b.image_id, both)
            db.write_two_view_geometry(a.image_id, b.image_id, g)
            added += len(m)
            verified += int(len(g.inlier_matches) > 0)
            advance()
    return {"images": len(involved), "pairs": len(pairs), "matches_added": added, "verified_pairs": verified}
