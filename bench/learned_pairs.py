"""Every pair of a scene's views matched by SIFT and by each learned detector, scored against the true poses (issue 44).

    python -m bench learned_pairs --out bench/results/learned_pairs.json   # lego, chair; 1 thread

Per scene: the 20 views ``bench poses`` takes (evenly spaced over the train split), every pair of them.
Matches: SIFT as ``process`` runs it (pycolmap: its default SIFT options, exhaustive matching, the pair's
verified inliers), and each learned detector of :data:`omnirecon.capture.learned.DETECTORS` with its
LightGlue (:class:`omnirecon.capture.learned.LearnedMatcher`, all matches). One estimator for all: the
pair's relative pose from its matches with the true pinhole camera (pycolmap ``estimate_relative_pose``,
LO-RANSAC at 2 px); its rotation against the one the true poses give. A pair is *right* when it has 15+
RANSAC inliers and a rotation within 5 degrees, *wrong* when it has 15+ inliers and is further off (the
mapper would take it), and counted by the true angle between the two views. CPU seconds: this process at
one torch / COLMAP thread, features per image and matching per pair. Also the two groups of views no
right pair joins: per scene, the largest set of views joined by right pairs, and the closest true angle and
most inliers of any pair between it and the rest.
"""

from __future__ import annotations

import itertools
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.poses import SHARED, pick_views, scene_parser, start

SCENES = ("blender/lego", "blender/chair")
BINS = ((0, 30), (30, 45), (45, 60), (60, 90), (90, 181))
"""True angles between the two views of a pair (degrees), [lo, hi)."""
MIN_INLIERS = 15
RIGHT_DEG = 5.0


def relative_errors(kp: dict, matches: dict, camera, c2w: np.ndarray, seed: int) -> dict:
    """Per pair ``(a, b)``: inliers and the rotation error (degrees) of the relative pose from ``matches[(a, b)]``
    ``[M, 2]`` (indices into ``kp[a]``, ``kp[b]``, COLMAP pixel convention)."""
    import pycolmap

    from omnirecon.capture.consistency import rotation_angle_deg

    out = {}
    for (a, b), m in matches.items():
        true = np.linalg.inv(c2w[b]) @ c2w[a]  # [4, 4] b <- a
        row = {"matches": int(len(m)), "inliers": 0, "error_deg": None,
               "angle_deg": round(rotation_angle_deg(true[:3, :3]), 2)}
        if len(m) >= 8:
            est = pycolmap.estimate_relative_pose(camera, kp[a][m[:, 0]], camera, kp[b][m[:, 1]],
                                                  pycolmap.RANSACOptions(max_error=2.0, random_seed=seed))
            if est is not None:
                row["inliers"] = int(np.count_nonzero(est["inlier_mask"]))
                row["error_deg"] = round(rotation_angle_deg(est["cam2_from_cam1"].rotation.matrix() @ true[:3, :3].T), 3)
        out[(a, b)] = row
    return out


def sift_pairs(image_dir: Path, names: list[str], work: Path, threads: int, seed: int) -> tuple[dict, dict, dict]:
    """SIFT keypoints and the verified inlier matches of every pair, as ``process`` extracts and matches them."""
    import pycolmap

    from omnirecon.capture.colmap_sfm import SfmOptions, Stages, _extract, _match, _quiet_colmap

    _quiet_colmap()
    options = SfmOptions(threads=threads, seed=seed)
    db = work / "database.db"
    pairs = list(itertools.combinations(range(len(names)), 2))
    c0 = time.process_time()
    with Stages(quiet=True) as stages:
        _extract(db, image_dir, names, options, stages, None, False)
        c1 = time.process_time()
        _match(db, work, names, pairs, options, stages)
    c2 = time.process_time()
    kp, matches = {}, {}
    with pycolmap.Database.open(str(db)) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        for i, n in enumerate(names):
            kp[i] = np.asarray(d.read_keypoints(ids[n]), np.float64)[:, :2]
        for a, b in pairs:
            ia, ib = ids[names[a]], ids[names[b]]
            g = d.read_two_view_geometry(ia, ib) if d.exists_two_view_geometry(ia, ib) else None
            m = np.zeros((0, 2), np.int64) if g is None else np.asarray(g.inlier_matches, np.int64).reshape(-1, 2)
            if g is not None and ia > ib:  # stored in id order
                m = m[:, ::-1]
            matches[(a, b)] = m
    return kp, matches, {"features_cpu_s_per_image": round((c1 - c0) / len(names), 3),
                         "matching_cpu_s_per_pair": round((c2 - c1) / len(pairs), 3)}


def learned_pairs(image_dir: Path, names: list[str], method: str) -> tuple[dict, dict, dict]:
    """Learned keypoints and LightGlue's matches of every pair; ``method``: a detector name, optionally
    ``:<most keypoints>`` (default :class:`omnirecon.capture.learned.LearnedMatcher`'s)."""
    from omnirecon.capture.learned import LearnedMatcher

    detector, _, most = method.partition(":")
    m = LearnedMatcher(detector=detector, **({"max_keypoints": int(most)} if most else {}))
    c0 = time.process_time()
    feats = {i: m.features(image_dir / n) for i, n in enumerate(names)}
    c1 = time.process_time()
    matches = {(a, b): m.match(feats[a], feats[b]).astype(np.int64)
               for a, b in itertools.combinations(range(len(names)), 2)}
    c2 = time.process_time()
    kp = {i: f.keypoints for i, f in feats.items()}
    return kp, matches, {"features_cpu_s_per_image": round((c1 - c0) / len(names), 3),
                         "matching_cpu_s_per_pair": round((c2 - c1) / len(matches), 3),
                         "keypoints_median": int(np.median([len(k) for k in kp.values()]))}


def summarize(pairs: dict, n: int) -> dict:
    """Right / wrong pairs per angle bin; the largest group of views joined by right pairs and its best bridge."""
    bins = []
    for lo, hi in BINS:
        sel = [r for r in pairs.values() if lo <= r["angle_deg"] < hi]
        took = [r for r in sel if r["inliers"] >= MIN_INLIERS and r["error_deg"] is not None]
        right = [r for r in took if r["error_deg"] < RIGHT_DEG]
        wrong = [r for r in took if r["error_deg"] >= RIGHT_DEG]
        bins.append({"lo": lo, "hi": hi, "pairs": len(sel), "right": len(right), "wrong": len(wrong),
                     "wrong_inliers_max": max((r["inliers"] for r in wrong), default=0),
                     "right_inliers_median": int(np.median([r["inliers"] for r in right])) if right else 0})
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for (a, b), r in pairs.items():
        if r["inliers"] >= MIN_INLIERS and r["error_deg"] is not None and r["error_deg"] < RIGHT_DEG:
            parent[root(a)] = root(b)
    groups = {}
    for i in range(n):
        groups.setdefault(root(i), []).append(i)
    big = set(max(groups.values(), key=len))
    across = [r for (a, b), r in pairs.items() if (a in big) != (b in big)]
    return {"bins": bins, "largest_right_group": len(big), "views": n,
            "closest_angle_across_deg": min((r["angle_deg"] for r in across), default=None),
            "right_across": sum(1 for r in across if r["inliers"] >= MIN_INLIERS and r["error_deg"] is not None
                                and r["error_deg"] < RIGHT_DEG),
            "wrong_across_inliers_max": max((r["inliers"] for r in across if r["inliers"] >= MIN_INLIERS
                                             and (r["error_deg"] or 0) >= RIGHT_DEG), default=0)}


def run_scene(path: Path, images: int, methods: list[str], work: Path, threads: int, seed: int) -> list[dict]:
    import pycolmap

    from omnirecon.data import load_scene

    ref = load_scene(path)
    views = pick_views(ref, images)
    folder = work / "photos"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    names = []
    for i in views:
        src = Path(ref.path) / ref.names[i]
        names.append(f"{len(names):03d}_{src.name}")
        shutil.copyfile(src, folder / names[-1])
    c2w = ref.cameras.c2w[views].numpy().astype(np.float64)
    f, cx, cy = float(ref.cameras.fx[views[0]]), float(ref.cameras.cx[views[0]]), float(ref.cameras.cy[views[0]])
    camera = pycolmap.Camera(model="PINHOLE", width=ref.width, height=ref.height, params=[f, f, cx, cy])
    rows = []
    for method in methods:
        t0, load = time.perf_counter(), round(os.getloadavg()[0], 2)
        shutil.rmtree(work / "sift", ignore_errors=True)
        (work / "sift").mkdir()
        kp, matches, cost = sift_pairs(folder, names, work / "sift", threads, seed) if method == "sift" \
            else learned_pairs(folder, names, method)
        pairs = relative_errors(kp, matches, camera, c2w, seed)
        rows.append({"scene": path.name, "path": str(path.relative_to(SHARED)), "method": method, "images": len(views),
                     "size": [ref.width, ref.height], "load_1min_start": load,
                     "seconds": round(time.perf_counter() - t0, 2), **cost, **summarize(pairs, len(views)),
                     "pairs": [{"a": a, "b": b, **r} for (a, b), r in pairs.items()]})
        s = rows[-1]
        print(f"{s['scene']} {method}: right/wrong per bin "
              f"{[(b['right'], b['wrong']) for b in s['bins']]}, group {s['largest_right_group']}/{s['views']}, "
              f"{cost}", flush=True)
    return rows


def main(argv: list[str] | None = None) -> dict:
    parser = scene_parser(__doc__, list(SCENES), "learned_pairs.json")
    parser.add_argument("--methods", nargs="+", default=["sift", "aliked", "aliked:1024", "disk"],
                        help="sift, or a learned detector (omnirecon.capture.learned.DETECTORS) with an optional "
                             ":<most keypoints per image>")
    args = parser.parse_args(argv)
    prov = start(args.threads, args.seed)
    from omnirecon.data.io import write_json

    rows = []
    with tempfile.TemporaryDirectory(prefix="learned_pairs_") as tmp:
        for k, s in enumerate(args.scenes):
            if (SHARED / s).is_dir():
                rows += run_scene(SHARED / s, args.images, args.methods, Path(tmp) / f"s{k}", args.threads, args.seed)
    out = {"provenance": prov, "config": {"bins": [list(b) for b in BINS], "min_inliers": MIN_INLIERS,
                                          "right_deg": RIGHT_DEG, "ransac_px": 2.0}, "scenes": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.out, out)
    return out


if __name__ == "__main__":
    main()
