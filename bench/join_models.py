"""Join SIFT's separate models through learned matches, only where several pairs agree (an experiment,
``python -m bench pose_join``; not used by ``process``: on lego and chair it joined nothing, see BENCHMARKS).

SIFT can pose one capture as two or more models that share no pair of enough verified matches (a 360-degree
object capture whose sides look alike). A single learned match between them proves nothing: on a symmetric
object the front matches the back. :func:`join_models` therefore asks many pairs: each view of the smaller
model with its :data:`PARTNERS` most similar views of the larger one (visual words of their SIFT features,
:mod:`omnirecon.capture.retrieval`), matched with DISK + LightGlue (:mod:`omnirecon.capture.learned`). Each
pair's relative pose (:func:`pycolmap.estimate_relative_pose`, each model's own camera), with the two models'
poses of its views, gives a candidate rotation from the larger model's frame to the smaller's
(:func:`pair_candidate`) and a ray on which the larger model's camera centre lies in the smaller's frame.
The join is accepted only when the candidates of at least :data:`MIN_VIEWS` different views of the smaller
model agree within :data:`AGREE_DEG` and no other group of as many views agrees on another rotation
(:func:`consensus`: a front-to-back match gives a rotation about 180 degrees off); the scale and
translation then follow from the agreeing pairs' rays by least squares (:func:`similarity_from_rays`).
The second estimator poses each view of the smaller model against points :func:`triangulated` from the larger
model's own learned matches (:func:`pnp_candidates`: one rotation per view, the scale and translation from the
views' centres in both frames, :func:`similarity_from_centres`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

PARTNERS = 3
"""Views of the larger model each view of the smaller one is matched with (the most similar ones)."""
MIN_INLIERS = 15
"""Relative-pose inliers a pair needs to give a candidate (COLMAP's default for a verified pair)."""
MIN_VIEWS = 3
"""Different views of the smaller model whose candidates must agree before a join is accepted."""
AGREE_DEG = 5.0
"""Candidates agree when their rotations are within this angle (degrees)."""
MAX_ERROR_PX = 4.0
"""RANSAC threshold of the relative pose (pixels; COLMAP's two-view verification threshold)."""


def angle_deg(r: np.ndarray) -> float:
    """Angle in degrees of the rotation matrix ``r`` [3, 3]."""
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


@dataclass
class Candidate:
    """What one cross-model pair says about the similarity taking the larger model ``A`` into the smaller ``B``."""

    a: str
    b: str
    rotation: np.ndarray
    """[3, 3] world_A -> world_B rotation: ``R_b^T R_ab R_a``."""
    centre_a: np.ndarray
    """[3] view a's camera centre in A's frame."""
    centre_b: np.ndarray
    """[3] view b's camera centre in B's frame."""
    direction: np.ndarray
    """[3] unit direction, in B's frame, from view b's centre towards view a's (the pair's baseline)."""
    inliers: int


def pair_candidate(a: str, b: str, r_a: np.ndarray, t_a: np.ndarray, r_b: np.ndarray, t_b: np.ndarray,
                   r_ab: np.ndarray, t_ab: np.ndarray, inliers: int) -> Candidate:
    """The :class:`Candidate` of the pair from world-to-camera poses ``x = R X + t`` of view a in model A
    (``r_a`` [3, 3], ``t_a`` [3]) and of view b in model B, and the pair's relative pose
    ``x_b = r_ab x_a + t_ab`` (``t_ab`` up to scale)."""
    t_ab = np.asarray(t_ab, np.float64) / max(np.linalg.norm(t_ab), 1e-12)
    return Candidate(a, b, r_b.T @ r_ab @ r_a, -r_a.T @ t_a, -r_b.T @ t_b, r_b.T @ t_ab, int(inliers))


def consensus(cands: list[Candidate], agree_deg: float = AGREE_DEG, min_views: int = MIN_VIEWS) -> dict:
    """The largest group of candidates whose rotations agree within ``agree_deg`` of one of them, counted in
    distinct views of B. Accepted when it holds ``min_views`` views or more and no candidate outside it from
    as many views agrees on another rotation. Returns ``accepted``, ``members`` (indices), ``views``,
    ``rival_views`` (views of the best group disagreeing with it), ``spread_deg`` (members' largest angle to
    their mean) and ``rotation`` (the members' chordal mean [3, 3], or None)."""
    best, best_views = [], 0
    for c in cands:
        group = [j for j, d in enumerate(cands) if angle_deg(c.rotation @ d.rotation.T) < agree_deg]
        views = len({cands[j].b for j in group})
        if views > best_views or (views == best_views and len(group) > len(best)):
            best, best_views = group, views
    rival = 0
    for c in cands:
        if any(angle_deg(c.rotation @ cands[j].rotation.T) < 2 * agree_deg for j in best):
            continue
        group = [d for d in cands if angle_deg(c.rotation @ d.rotation.T) < agree_deg]
        rival = max(rival, len({d.b for d in group}))
    out = {"members": best, "views": best_views, "rival_views": rival, "rotation": None, "spread_deg": None,
           "accepted": best_views >= min_views and rival < best_views}
    if best:
        u, _, vt = np.linalg.svd(sum(cands[j].rotation for j in best))
        rot = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
        out["rotation"] = rot
        out["spread_deg"] = max(angle_deg(rot @ cands[j].rotation.T) for j in best)
    return out


def similarity_from_rays(rot: np.ndarray, cands: list[Candidate]) -> tuple[float, np.ndarray] | None:
    """Scale ``s`` and translation ``u`` [3] of ``X_B = s rot X_A + u`` from the pairs' rays: view a's centre,
    carried into B, lies on the ray from view b's centre along the pair's direction (``s rot c_a + u =
    c_b + l d``, ``l > 0``). Least squares over ``s``, ``u`` and each ``l``; None when under two pairs,
    or the scale or a depth comes out non-positive."""
    n = len(cands)
    if n < 2:
        return None
    m = np.zeros((3 * n, 4 + n))
    y = np.zeros(3 * n)
    for i, c in enumerate(cands):
        rows = slice(3 * i, 3 * i + 3)
        m[rows, 0] = rot @ c.centre_a
        m[rows, 1:4] = np.eye(3)
        m[rows, 4 + i] = -c.direction
        y[rows] = c.centre_b
    sol, *_ = np.linalg.lstsq(m, y, rcond=None)
    if sol[0] <= 0 or np.any(sol[4:] <= 0):
        return None
    return float(sol[0]), sol[1:4]


def similarity_from_centres(rot: np.ndarray, cands: list[Candidate]) -> tuple[float, np.ndarray] | None:
    """Scale ``s`` and translation ``u`` [3] of ``X_B = s rot X_A + u`` from views posed in both frames
    (``centre_a`` in A, ``centre_b`` in B; least squares); None when under two, or the scale is not positive."""
    if len(cands) < 2:
        return None
    a = np.stack([rot @ c.centre_a for c in cands])  # [K, 3]
    b = np.stack([c.centre_b for c in cands])  # [K, 3]
    a0, b0 = a - a.mean(0), b - b.mean(0)
    s = float((a0 * b0).sum() / max((a0 ** 2).sum(), 1e-300))
    return (s, b.mean(0) - s * a.mean(0)) if s > 0 else None


@dataclass
class Join:
    """A tried join of model B into model A."""

    accepted: bool
    pairs: int
    candidates: list[dict] = field(default_factory=list)
    """Each pair with enough inliers: names, inliers, angle to the accepted rotation (degrees)."""
    consensus: dict = field(default_factory=dict)
    scale: float | None = None
    rotation: np.ndarray | None = None
    """[3, 3] world_A -> world_B."""
    translation: np.ndarray | None = None
    reason: str = ""
    found: list[Candidate] = field(default_factory=list)
    """The candidates themselves (same order as ``candidates``)."""


def candidate_pairs(sim: np.ndarray, index: dict[str, int], a_names: list[str], b_names: list[str],
                    k: int = PARTNERS) -> list[tuple[str, str]]:
    """Each of ``b_names`` with its ``k`` most similar of ``a_names`` (``sim`` [N, N] over ``index``)."""
    out = []
    for b in b_names:
        scores = [(-sim[index[b], index[a]], a) for a in a_names]
        out += [(a, b) for _, a in sorted(scores)[:k]]
    return out


def estimate_join(rec_a, rec_b, pairs: list[tuple[str, str]], feats: dict, match, seed: int = 0) -> Join:
    """Try to join pycolmap models ``rec_b`` into ``rec_a`` through the ``pairs`` (name in A, name in B),
    ``feats``: name -> :class:`omnirecon.capture.learned.Features`; ``match(a, b)``: [M, 2] indices into
    both images' learned features (LightGlue)."""
    import pycolmap  # lazy: the optional 'capture' extra

    ransac = pycolmap.RANSACOptions()
    ransac.max_error = MAX_ERROR_PX
    ransac.random_seed = seed
    by_a = {im.name: im for im in rec_a.images.values() if im.has_pose}
    by_b = {im.name: im for im in rec_b.images.values() if im.has_pose}
    cands = []
    for a, b in pairs:
        m = match(a, b)  # [M, 2]
        if len(m) < MIN_INLIERS:
            continue
        ia, ib = by_a[a], by_b[b]
        pa, pb = feats[a].keypoints[m[:, 0]], feats[b].keypoints[m[:, 1]]  # [M, 2] pixels
        rel = pycolmap.estimate_relative_pose(rec_a.cameras[ia.camera_id], pa, rec_b.cameras[ib.camera_id], pb, ransac)
        if rel is None or rel["num_inliers"] < MIN_INLIERS:
            continue
        pose_a, pose_b, ab = ia.cam_from_world(), ib.cam_from_world(), rel["cam2_from_cam1"]
        cands.append(pair_candidate(a, b, pose_a.rotation.matrix(), np.asarray(pose_a.translation),
                                    pose_b.rotation.matrix(), np.asarray(pose_b.translation),
                                    ab.rotation.matrix(), np.asarray(ab.translation), rel["num_inliers"]))
    return decide(cands, len(pairs))


def decide(cands: list[Candidate], pairs: int, centres: bool = False) -> Join:
    """The :class:`Join` the candidates support (see :func:`consensus`; scale and translation by
    :func:`similarity_from_rays`, or with ``centres`` from each view's centre in both frames,
    :func:`similarity_from_centres`)."""
    cons = consensus(cands)
    rot = cons["rotation"]
    rows = [{"a": c.a, "b": c.b, "inliers": c.inliers,
             "deg_off": None if rot is None else round(angle_deg(rot @ c.rotation.T), 2)} for c in cands]
    summary = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in cons.items() if k != "rotation"}
    join = Join(False, pairs, rows, summary, found=cands)
    if not cons["accepted"]:
        join.reason = (f"{cons['views']} views agree (need {MIN_VIEWS}), {cons['rival_views']} on another rotation")
        return join
    sim = (similarity_from_centres if centres else similarity_from_rays)(rot, [cands[j] for j in cons["members"]])
    if sim is None:
        join.reason = "the agreeing pairs' baselines give no positive scale"
        return join
    join.accepted, join.scale, join.rotation, join.translation = True, sim[0], rot, sim[1]
    return join


def joined_poses(rec_b, join: Join) -> dict[str, np.ndarray]:
    """World-to-camera poses [3, 4] of model B's views in model A's frame after ``join`` (accepted):
    ``x = R_b (s Q X_A + u) + t_b``, divided by ``s``."""
    out = {}
    for im in rec_b.images.values():
        if not im.has_pose:
            continue
        p = im.cam_from_world()
        r_b, t_b = p.rotation.matrix(), np.asarray(p.translation)
        out[im.name] = np.concatenate([r_b @ join.rotation, ((r_b @ join.translation + t_b) / join.scale)[:, None]], 1)
    return out


def triangulated(rec_a, pairs: list[tuple[str, str]], feats: dict, match, max_px: float = MAX_ERROR_PX,
                 min_angle_deg: float = 2.0) -> dict[tuple[str, int], np.ndarray]:
    """3-D points in model A's frame of the learned matches of ``pairs`` of A's views (their poses held fixed):
    ``{(name, keypoint index): [3]}`` for each match triangulated (DLT) within ``max_px`` in both views, in
    front of both, with rays at least ``min_angle_deg`` apart."""
    by = {im.name: im for im in rec_a.images.values() if im.has_pose}
    out = {}
    for a, b in pairs:
        m = match(a, b)
        if len(m) < MIN_INLIERS:
            continue
        views = []
        for n, idx in ((a, m[:, 0]), (b, m[:, 1])):
            im = by[n]
            cam, pose = rec_a.cameras[im.camera_id], np.asarray(im.cam_from_world().matrix())  # [3, 4]
            views.append((cam, pose, np.asarray(cam.cam_from_img(feats[n].keypoints[idx]), np.float64)))  # [M, 2]
        rows = np.concatenate([np.stack([x[:, :1] * p[2] - p[0], x[:, 1:] * p[2] - p[1]], 1)
                               for _, p, x in views], 1)  # [M, 4, 4]
        x4 = np.linalg.svd(rows)[2][:, -1]  # [M, 4]
        pts = x4[:, :3] / np.where(np.abs(x4[:, 3:]) > 1e-12, x4[:, 3:], 1e-12)  # [M, 3]
        ok = np.ones(len(m), bool)
        rays = []
        for cam, p, x in views:
            cam_pts = pts @ p[:, :3].T + p[:, 3]  # [M, 3]
            err = np.linalg.norm(cam_pts[:, :2] / np.maximum(cam_pts[:, 2:], 1e-12) - x, axis=1) * cam.mean_focal_length()
            ok &= (cam_pts[:, 2] > 0) & (err < max_px)
            centre = -p[:, :3].T @ p[:, 3]
            rays.append((pts - centre) / np.maximum(np.linalg.norm(pts - centre, axis=1, keepdims=True), 1e-12))
        ok &= np.einsum("mi,mi->m", *rays) < np.cos(np.radians(min_angle_deg))
        for k in np.flatnonzero(ok):
            out.setdefault((a, int(m[k, 0])), pts[k])
            out.setdefault((b, int(m[k, 1])), pts[k])
    return out


def pnp_candidates(rec_a, rec_b, points: dict, partners: dict[str, list[str]], feats: dict, match,
                   seed: int = 0) -> list[Candidate]:
    """One :class:`Candidate` per view b of model B posed in A's frame from its learned matches to the
    ``partners[b]`` views of A whose keypoints hold a :func:`triangulated` point (2-D to 3-D, LO-RANSAC and
    refinement, :func:`pycolmap.estimate_and_refine_absolute_pose`, B's camera)."""
    import pycolmap  # lazy: the optional 'capture' extra

    opts = pycolmap.AbsolutePoseEstimationOptions()
    opts.ransac.max_error = MAX_ERROR_PX
    opts.ransac.random_seed = seed
    out = []
    for im in rec_b.images.values():
        if not im.has_pose or im.name not in partners:
            continue
        seen, xy, xyz = set(), [], []
        for a in partners[im.name]:
            for ia, ib in match(a, im.name):
                if (a, int(ia)) in points and int(ib) not in seen:
                    seen.add(int(ib))
                    xy.append(feats[im.name].keypoints[ib])
                    xyz.append(points[(a, int(ia))])
        if len(xy) < MIN_INLIERS:
            continue
        got = pycolmap.estimate_and_refine_absolute_pose(np.array(xy), np.array(xyz), rec_b.cameras[im.camera_id], opts)
        if got is None or got["num_inliers"] < MIN_INLIERS:
            continue
        p_a, p_b = got["cam_from_world"], im.cam_from_world()
        r_a, r_b = p_a.rotation.matrix(), p_b.rotation.matrix()
        out.append(Candidate("pnp", im.name, r_b.T @ r_a, -r_a.T @ np.asarray(p_a.translation),
                             -r_b.T @ np.asarray(p_b.translation), np.zeros(3), int(got["num_inliers"])))
    return out
