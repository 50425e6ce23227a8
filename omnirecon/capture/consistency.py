"""No pose is better than a wrong one: registered views whose pose contradicts their verified pairs.

COLMAP's mapper can place a view the wrong way round and still count it registered: on a symmetric
object, matches between opposite sides make a pose flipped about 180 degrees fit enough points. Each
verified image pair in the database holds the inlier matches of its own two-view geometry.
:func:`pair_checks` asks, per pair of registered views, which share of those inliers the model's
relative pose explains (the essential matrix of the two model poses, the cameras' own calibration:
Sampson error within :data:`MAX_ERROR_PX`, and the point in front of both cameras), and the angle
between the model's relative rotation and the one re-estimated from the inliers alone.

The share, not the angle, decides: on a near-planar pair the essential matrix has two solutions that
explain the inliers equally well, so the re-estimated rotation is often the other one (on a 12-view
procedural capture whose poses were 0.5 degrees from the truth, a quarter of the pairs' re-estimated
rotations were 13-175 degrees off the model's), while both solutions, and so the correct model, explain
the inliers. A flipped or mirrored view explains almost none of its pairs' inliers.
:func:`inconsistent_views` drops, worst first, every view whose pairs (weighted by their inliers)
the model explains less than a threshold; :func:`check_poses` de-registers them with one reason each.

A group of views can be wrong together: on a symmetric object, learned matches can join views that SIFT
posed apart to the rest through pairs that match the front to the back, and the group comes out turned
about 180 degrees while each of its own pairs is explained (BENCHMARKS "Pose recovery": lego, chair).
:func:`contested_groups` finds such joins: a group the caller knows was posed apart (SIFT's separate
models, joined by learned matches) when a quarter of the pairs between it and the rest contradict the
model, and a side of two or more views that a bridge (the one explained pair between the two sides) joins
while another verified pair across contradicts it (one pair for and one against is no evidence).
The group goes, not the rest (no pose is better than a wrong one).

A flipped group can also be explained by every pair it has: on lego, with ALIKED's learned matches, SIFT's
separate model of 5 views was joined turned about 180 degrees through front-to-back matches, and no verified
pair contradicts it, since the views it truly neighbours share no match with it at all. What contradicts it
is that silence: :func:`silent_pairs` finds the pairs the model places looking at the same part of the scene
from nearby (optical axes within :data:`NEAR_DEG`, centres closer than :data:`NEAR_DEPTH` of their scene
depth) that were matched and share fewer than the verified matches a pair needs. Views that close match
where the photos are right (``python -m bench learned_pairs``: SIFT's inliers of every pair by the true angle
between the views; a correct model of dtu_scan37 holds pairs 23-24 degrees apart with none), and where both
views match some other view richly (:data:`RICH`): between images with few features (a 128-px procedural
capture's best pairs hold 18-42 matches) silence is no evidence. Each counts as a pair the model does not
explain, weighted as the fewest verified matches a pair needs, so a view's strongly matched pairs outweigh it.

The same rule across models: a retry's model replaces the one SfM has only when it poses more images with the same
poses on those both hold (:func:`agreement`, :func:`replaces`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

AGREE_DEG = (2.0, 5.0)
"""A retry's model replaces the current one only if, on the images both pose, their rotations agree
to this median and maximum (degrees) after a similarity alignment: more images, never other poses.
One exception: when the affine-feature model poses exactly as many images as the first one and they
disagree, the affine one is kept (affine-adapted descriptors are the less ambiguous; on 20 views of
Blender's chair the first model was 9.4 degrees off, the affine one 0.2). A model of fewer than half
the images is not protected (:func:`replaces`)."""
MAX_ERROR_PX = 4.0
"""Sampson distance (pixels, at the camera's mean focal length) below which the model explains a
match: COLMAP's own two-view verification threshold."""


@dataclass
class PairCheck:
    """One verified pair of registered views and how well the model's relative pose fits it."""

    a: str
    b: str
    explained: float
    """Share of the pair's verified matches the model's relative pose explains (0..1)."""
    inliers: int
    """Verified matches of the pair (the weight of its vote)."""
    degrees: float | None = None
    """Angle between the model's relative rotation and the one re-estimated from the inliers (for the
    record: ambiguous on near-planar pairs, see the module's note); None when none was found."""
    silent: bool = False
    """A pair the model places close (:func:`silent_pairs`) that shares too few verified matches: it counts
    as unexplained, with ``inliers`` the matches it should have had; ``degrees`` is the angle between the
    two optical axes in the model."""


def rotation_angle_deg(r: np.ndarray) -> float:
    """Angle in degrees of the rotation matrix ``r`` [3, 3]."""
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def explained_share(xa: np.ndarray, xb: np.ndarray, rot: np.ndarray, t: np.ndarray, focal: float,
                    max_px: float = MAX_ERROR_PX) -> float:
    """Share of the correspondences ``xa``, ``xb`` [M, 2] (normalized camera coordinates) that the relative
    pose ``x_b = rot @ x_a + t`` explains: Sampson distance below ``max_px`` / ``focal`` and the
    triangulated point in front of both cameras."""
    ha = np.concatenate([xa, np.ones((len(xa), 1))], 1)  # [M, 3]
    hb = np.concatenate([xb, np.ones((len(xb), 1))], 1)  # [M, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    e = tx @ rot  # [3, 3] essential matrix b <- a
    ea, eb = ha @ e.T, hb @ e  # [M, 3] epipolar lines in b and in a
    num = np.einsum("mi,mi->m", hb, ea) ** 2
    den = ea[:, 0] ** 2 + ea[:, 1] ** 2 + eb[:, 0] ** 2 + eb[:, 1] ** 2
    sampson = np.sqrt(num / np.maximum(den, 1e-18))  # [M] normalized units
    ra = ha @ rot.T  # [M, 3] rays of a in b's frame: depth_a * ra + t = depth_b * hb
    a_mat = np.stack([ra, -hb], 2)  # [M, 3, 2]
    ata = np.einsum("mki,mkj->mij", a_mat, a_mat) + 1e-12 * np.eye(2)  # [M, 2, 2] normal equations
    depths = np.linalg.solve(ata, np.einsum("mki,k->mi", a_mat, -t)[..., None])[..., 0]  # [M, 2] depth in a, b
    ok = (sampson * focal < max_px) & (depths[:, 0] > 0) & (depths[:, 1] > 0)
    return float(ok.mean()) if len(ok) else 0.0


def pair_checks(db_path: Path, rec, min_matches: int = 15, seed: int = 0) -> list[PairCheck]:
    """:class:`PairCheck` of every pair of the database ``db_path`` with at least ``min_matches`` verified
    matches whose two images are both registered in ``rec`` (a pycolmap.Reconstruction)."""
    import pycolmap  # lazy: the optional 'capture' extra

    posed = {rec.images[i].name: rec.images[i] for i in rec.reg_image_ids()}
    out = []
    with pycolmap.Database.open(str(db_path)) as db:
        names = {im.image_id: im.name for im in db.read_all_images()}
        keypoints: dict[int, np.ndarray] = {}
        pair_ids, geometries = db.read_two_view_geometries()
        for pid, g in zip(pair_ids, geometries):
            a, b = pycolmap.pair_id_to_image_pair(pid) if isinstance(pid, int) else pid
            m = np.asarray(g.inlier_matches)  # [M, 2] feature indices in a, b
            if len(m) < min_matches or names.get(a) not in posed or names.get(b) not in posed:
                continue
            for i in (a, b):
                if i not in keypoints:
                    keypoints[i] = np.asarray(db.read_keypoints(i))[:, :2].astype(np.float64)  # [K, 2] pixels
            ia, ib = posed[names[a]], posed[names[b]]
            ca, cb = rec.cameras[ia.camera_id], rec.cameras[ib.camera_id]
            pa, pb = keypoints[a][m[:, 0]], keypoints[b][m[:, 1]]  # [M, 2]
            rel = ib.cam_from_world() * ia.cam_from_world().inverse()  # b <- a
            rot, t = rel.rotation.matrix(), np.asarray(rel.translation)
            share = explained_share(ca.cam_from_img(pa), cb.cam_from_img(pb), rot, t / max(np.linalg.norm(t), 1e-12),
                                    0.5 * (ca.mean_focal_length() + cb.mean_focal_length()))
            est = pycolmap.estimate_relative_pose(ca, pa, cb, pb, pycolmap.RANSACOptions(max_error=MAX_ERROR_PX,
                                                                                          random_seed=seed))
            deg = None if est is None else rotation_angle_deg(rot @ est["cam2_from_cam1"].rotation.matrix().T)
            out.append(PairCheck(names[a], names[b], share, len(m), deg))
    return out


NEAR_DEG = 20.0
"""Silent pairs: the model's two optical axes within this angle (degrees)..."""
NEAR_DEPTH = 0.5
"""...and the two camera centres closer than this fraction of the smaller of the two views' median depth of
their 3-D points."""
RICH = 4
"""Silent pairs: each of the two views has a verified pair with at least this many times the matches a pair
needs (a view that matches nothing richly says nothing by not matching)."""


def silent_pairs(db_path: Path, rec, min_matches: int = 15) -> list[PairCheck]:
    """Pairs of views registered in ``rec`` that the model places close (:data:`NEAR_DEG`, :data:`NEAR_DEPTH`)
    and that the database ``db_path`` matched, with fewer than ``min_matches`` verified matches, both views
    matching some view richly (:data:`RICH`; see the module's note). Pairs never matched (retrieval or
    sequential matching left them out) are no evidence."""
    import pycolmap  # lazy: the optional 'capture' extra

    views = {}
    for i in rec.reg_image_ids():
        im = rec.images[i]
        pose = im.cam_from_world()
        rot, centre = pose.rotation.matrix(), np.asarray(im.projection_center())
        xyz = np.asarray([rec.points3D[p.point3D_id].xyz for p in im.points2D if p.has_point3D()]).reshape(-1, 3)
        if len(xyz):
            views[im.name] = (rot[2], centre, float(np.median((xyz - centre) @ rot[2])))  # axis, centre, depth
    out = []
    with pycolmap.Database.open(str(db_path)) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        richest = dict.fromkeys(ids.values(), 0)  # image id -> most verified matches of one of its pairs
        pair_ids, geometries = db.read_two_view_geometries()
        for pid, g in zip(pair_ids, geometries):
            for i in pycolmap.pair_id_to_image_pair(pid) if isinstance(pid, int) else pid:
                richest[i] = max(richest.get(i, 0), len(g.inlier_matches))
        names = sorted(n for n in views if richest.get(ids[n], 0) >= RICH * min_matches)
        for k, a in enumerate(names):
            for b in names[k + 1:]:
                (fa, ca, da), (fb, cb, dbb) = views[a], views[b]
                axes = float(np.degrees(np.arccos(np.clip(fa @ fb, -1.0, 1.0))))
                if axes >= NEAR_DEG or np.linalg.norm(ca - cb) >= NEAR_DEPTH * min(da, dbb) or min(da, dbb) <= 0:
                    continue
                ia, ib = ids[a], ids[b]
                if not db.exists_matches(ia, ib):
                    continue
                got = len(db.read_two_view_geometry(ia, ib).inlier_matches) if db.exists_two_view_geometry(ia, ib) else 0
                if got < min_matches:
                    out.append(PairCheck(a, b, 0.0, min_matches, axes, silent=True))
    return out


def weighted_median(values: list[float], weights: list[int]) -> float:
    """The value below which half of the total weight lies."""
    order = np.argsort(values)
    v, w = np.asarray(values)[order], np.cumsum(np.asarray(weights, dtype=np.float64)[order])
    return float(v[np.searchsorted(w, w[-1] / 2.0)])


def inconsistent_views(checks: list[PairCheck], min_share: float) -> dict[str, tuple[float, int]]:
    """Views to drop: repeatedly the one the model explains worst (median share over its pairs, weighted
    by verified matches) while that median is below ``min_share``; a dropped view's pairs no longer count
    against its partners. Returns ``{name: (median share, pairs)}`` in the order dropped."""
    left = list(checks)
    dropped: dict[str, tuple[float, int]] = {}
    while left:
        per: dict[str, list[PairCheck]] = {}
        for c in left:
            per.setdefault(c.a, []).append(c)
            per.setdefault(c.b, []).append(c)
        score = {n: weighted_median([c.explained for c in cs], [c.inliers for c in cs]) for n, cs in per.items()}
        worst = min(sorted(score), key=lambda n: score[n])
        if score[worst] >= min_share:
            break
        dropped[worst] = (score[worst], len(per[worst]))
        left = [c for c in left if worst not in (c.a, c.b)]
    return dropped


@dataclass
class ContestedJoin:
    """A group of views joined to the rest while verified pairs between them contradict the join."""

    views: list[str]
    """The group: the views dropped."""
    support: list[PairCheck]
    """The pairs between the group and the rest that the model explains."""
    against: list[PairCheck]
    """The pairs between the group and the rest that the model does not explain."""


CONTESTED = 0.25
"""Share of the pairs between a group and the rest that, unexplained, makes the join contested. A bridge (one
explained pair) is contested by any pair against it; in a correct model, unexplained pairs are a few outliers
spread over the graph, not a quarter of one cut."""


def contested_groups(checks: list[PairCheck], min_share: float, groups: list[list[str]] = ()) -> list[ContestedJoin]:
    """Groups to drop (see the module's note), found one at a time. The candidates: each of ``groups``
    (views the caller knows were posed apart, e.g. SIFT's separate models before learned matches joined
    them), then the smaller side (fewer views, then fewer verified matches) of each bridge of the graph of
    pairs the model explains (share >= ``min_share``) when it holds two views or more (a single view is
    judged by the median of its own pairs). A candidate goes when at least :data:`CONTESTED` of the pairs
    between it and the rest are not explained; the search repeats on the rest."""
    import networkx as nx  # a dependency of torch

    left, out = list(checks), []
    while True:
        g = nx.Graph()
        g.add_nodes_from(n for c in left for n in (c.a, c.b))
        g.add_edges_from((c.a, c.b) for c in left if c.explained >= min_share)
        inliers = {n: sum(c.inliers for c in left if n in (c.a, c.b)) for n in g}
        sides = [set(grp) & set(g) for grp in groups]
        for a, b in list(nx.bridges(g)):
            g.remove_edge(a, b)
            cut = nx.node_connected_component(g, a), nx.node_connected_component(g, b)
            g.add_edge(a, b)
            side = min(cut, key=lambda s: (len(s), sum(inliers[n] for n in s), sorted(s)))
            if len(side) > 1:  # a single view is judged by its own pairs (inconsistent_views)
                sides.append(side)
        found = None
        for side in sides:
            if not side or len(side) >= len(g):
                continue
            cross = [c for c in left if (c.a in side) != (c.b in side)]
            against = [c for c in cross if c.explained < min_share]
            if against and len(against) >= CONTESTED * len(cross):
                found = ContestedJoin(sorted(side), [c for c in cross if c.explained >= min_share], against)
                break
        if found is None:
            return out
        out.append(found)
        left = [c for c in left if c.a not in found.views and c.b not in found.views]


def check_poses(db_path: Path, rec, min_share: float, min_matches: int = 15, seed: int = 0,
                groups: list[list[str]] = ()) -> tuple[dict, dict]:
    """De-register from ``rec`` (in place) the views :func:`inconsistent_views` finds, then the groups
    :func:`contested_groups` finds among the rest (``groups``: its known candidates); returns one reason
    per dropped view and a summary (pairs checked, the median share explained, the views dropped)."""
    silent = silent_pairs(db_path, rec, min_matches)
    checks = pair_checks(db_path, rec, min_matches, seed) + silent
    bad = inconsistent_views(checks, min_share) if min_share > 0 else {}
    reasons = {}
    for name, (share, k) in bad.items():
        reasons[name] = (f"pose dropped: it contradicts its verified pairs (the model explains {share:.0%} of their "
                         f"matches, median of {k} pairs, views placed close that share no match counted as "
                         f"unexplained; {min_share:.0%} needed), e.g. a view placed the wrong way round on a "
                         "symmetric subject")
    rest = [c for c in checks if c.a not in bad and c.b not in bad]
    joins = contested_groups(rest, min_share, groups) if min_share > 0 else []
    for j in joins:
        worst = max(j.against, key=lambda c: (not c.silent, c.inliers))
        example = (f"{worst.a}-{worst.b}: placed {worst.degrees:.0f} deg apart yet sharing under {worst.inliers} "
                   "verified matches" if worst.silent else
                   f"{worst.a}-{worst.b}: the model explains {worst.explained:.0%} of its {worst.inliers} matches")
        for name in j.views:
            reasons[name] = (f"pose dropped: it is one of {len(j.views)} views ({', '.join(j.views[:4])}"
                             f"{', ...' if len(j.views) > 4 else ''}) joined to the others through {len(j.support)} "
                             f"pair(s) while {len(j.against)} other pair(s) between them contradict that join (e.g. "
                             f"{example}), e.g. a symmetric subject matched front to back")
    by_name = {rec.images[i].name: rec.images[i] for i in rec.reg_image_ids()}
    for name in reasons:
        rec.deregister_frame(by_name[name].frame_id)
    shares = [c.explained for c in checks if not c.silent]
    summary = {"pairs": len(checks) - len(silent), "silent_pairs": len(silent), "min_share": min_share,
               "dropped": list(reasons),
               "groups": [j.views for j in joins],
               "explained_median": round(float(np.median(shares)), 4) if shares else None,
               "explained_min": round(float(np.min(shares)), 4) if shares else None}
    return reasons, summary


def agreement(a, b) -> tuple[float, float] | None:
    """Median and largest rotation difference (degrees) between reconstructions ``a`` and ``b`` on the
    images both pose, after a similarity alignment; None when they share fewer than 3 images."""
    from omnirecon.capture.align import pose_errors

    def c2w(rec) -> dict:
        out = {}
        for i in rec.reg_image_ids():
            im = rec.images[i]
            m = np.eye(4)
            m[:3] = im.cam_from_world().inverse().matrix()  # [3, 4]
            out[im.name] = m
        return out

    pa, pb = c2w(a), c2w(b)
    common = sorted(set(pa) & set(pb))
    if len(common) < 3:
        return None
    e = pose_errors(np.stack([pb[n] for n in common]), np.stack([pa[n] for n in common]), 1.0)
    return round(e["rotation_deg_median"], 3), round(e["rotation_deg_max"], 3)


def replaces(current: int | None, candidate: int, agree: tuple[float, float] | None, affine: bool,
             total: int) -> bool:
    """Whether a retry's model (``candidate`` of ``total`` images) replaces the current one (``current``
    images, None when there is none): it must pose more images and agree (``agree``: median and largest
    rotation difference in degrees, :func:`agreement`; within :data:`AGREE_DEG`), or be the
    affine-feature model posing as many images and disagreeing (see :data:`AGREE_DEG`). A current
    model of fewer than half the images is not protected: any model with more images replaces it."""
    if current is None or 2 * current < total:
        return candidate > (current or 0)
    agrees = agree is not None and agree[0] <= AGREE_DEG[0] and agree[1] <= AGREE_DEG[1]
    return (candidate > current and agrees) or (affine and candidate == current > 0 and not agrees)
