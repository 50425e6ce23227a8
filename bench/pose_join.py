"""Joining SIFT's separate models through agreeing learned matches (issue 44), scored against the true poses.

    python -m bench pose_join --partners 0 --out bench/results/pose_join.json   # lego, then chair, 1 thread

Per scene: SIFT alone (``run_sfm``, ``learned = "off"``, the bench poses settings) on 20 evenly spaced views;
its kept model (after the pose check) is model A, the other models are read from every mapping's folder
(the largest first, disjoint from A and each other). Each other model of 3+ views is tried against A
(:mod:`bench.join_models`): each of its views with ``--partners`` views of A (the most similar by SIFT words;
0 = all), DISK + LightGlue matches, then two estimators: a rotation per pair from its relative pose, and a
rotation per view from its 2-D to 3-D matches against A's own triangulated learned matches; a join is
accepted when 3+ views agree within 5 degrees and no as large group agrees on another rotation. A joined
model's views get A's frame (no bundle adjustment of the union). Scored like ``bench poses`` (rotation and
centre errors after a similarity alignment to the true poses), and each candidate against the rotation the
true poses give.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.poses import SHARED, pick_views, scene_parser, start


def c2w(pose: np.ndarray) -> np.ndarray:
    """[4, 4] camera-to-world of the world-to-camera pose ``pose`` [3, 4]."""
    out = np.eye(4)
    out[:3, :3] = pose[:3, :3].T
    out[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return out


def poses_of(rec, keep: set[str] | None = None) -> dict[str, np.ndarray]:
    out = {}
    for im in rec.images.values():
        if im.has_pose and (keep is None or im.name in keep):
            out[im.name] = np.asarray(im.cam_from_world().matrix())
    return out


def frame(poses: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> np.ndarray:
    """[3, 3] rotation taking a model's world frame to the true one (chordal mean over its views of
    ``R_true^T R_model``)."""
    u, _, vt = np.linalg.svd(sum(np.linalg.inv(truth[n])[:3, :3].T @ p[:3, :3] for n, p in poses.items()))
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def score(poses: dict[str, np.ndarray], truth: dict[str, np.ndarray], extent: float) -> dict:
    from omnirecon.capture.align import pose_errors

    names = sorted(poses)
    err = pose_errors(np.stack([c2w(poses[n]) for n in names]), np.stack([truth[n] for n in names]), extent)
    return {"registered": len(names), **{k: round(err[k], 3) for k in ("rotation_deg_median", "rotation_deg_max",
                                                                       "centre_pct_median", "centre_pct_max")},
            "per_view_rotation_deg": {n: round(e, 2) for n, e in zip(names, err["rotation_deg"])}}


def run(path: Path, count: int, work: Path, threads: int, seed: int, partners: int) -> dict:
    import pycolmap

    from bench import join_models as join
    from omnirecon.capture import retrieval
    from omnirecon.capture.colmap_sfm import SfmOptions, Stages, run_sfm
    from omnirecon.capture.learned import LearnedMatcher
    from omnirecon.data import load_scene

    ref = load_scene(path)
    views = pick_views(ref, count)
    folder = work / "photos"
    folder.mkdir(parents=True)
    truth = {}
    for i in views:
        src = Path(ref.path) / ref.names[i]
        shutil.copyfile(src, folder / src.name)
        truth[src.name] = ref.cameras.c2w[i].numpy().astype(np.float64)
    names = sorted(truth)
    extent = float((ref.bounds[1] - ref.bounds[0]).double().norm())
    row = {"scene": path.name, "images": len(names), "load_1min_start": round(os.getloadavg()[0], 2)}
    options = SfmOptions(threads=threads, seed=seed, min_registered=0.0, learned="off")
    c0 = time.process_time()
    result = run_sfm(folder, names, work / "sfm", options, Stages(quiet=True))
    row["sift_cpu_seconds"] = round(time.process_time() - c0, 2)
    kept = next(k for k, a in enumerate(result.attempts) if a.get("kept"))
    # the separate models of every mapping (the relaxed one writes only the model it continued), largest first
    folders = sorted(p for p in (work / "sfm").glob("sparse_*/*") if p.is_dir())
    models = sorted((pycolmap.Reconstruction(p) for p in folders), key=lambda r: r.num_reg_images(), reverse=True)
    base = set(result.registered)
    others, taken = [], set(base)
    for m in models:  # disjoint from the kept model and from each other
        if m.num_reg_images() >= 3 and not set(poses_of(m)) & taken:
            others.append(m)
            taken |= set(poses_of(m))
    row["sift"] = score(poses_of(result.reconstruction, base), truth, extent)
    row["sift_models"] = [m.num_reg_images() for m in others]
    row["sift_attempt_kept"] = result.attempts[kept]["attempt"]
    c1 = time.process_time()
    sim = retrieval.similarity(work / "sfm" / "database.db", names, seed)  # [N, N]
    index = {n: i for i, n in enumerate(names)}
    matcher = LearnedMatcher(max_size=options.max_image_size)
    feats, cache = {}, {}

    def match(a: str, b: str) -> np.ndarray:  # [M, 2] LightGlue matches, each pair once
        for n in (a, b):
            if n not in feats:
                feats[n] = matcher.features(folder / n)
        if (a, b) not in cache:
            cache[(a, b)] = matcher.match(feats[a], feats[b]).astype(np.int64)
        return cache[(a, b)]

    a_poses = poses_of(result.reconstruction, base)
    joined = {"pairs": dict(a_poses), "pnp": dict(a_poses)}
    points, tries = None, []
    for m in others:
        pairs = join.candidate_pairs(sim, index, sorted(base), sorted(poses_of(m)), partners or len(base))
        own = score(poses_of(m), truth, extent)  # the separate model on its own, for reference
        q_true = frame(poses_of(m), truth).T @ frame(a_poses, truth)  # A -> B, from the true poses
        t = {"model_views": m.num_reg_images(), "pairs": len(pairs),
             "alone": {k: own[k] for k in ("rotation_deg_median", "rotation_deg_max")}}
        j = join.estimate_join(result.reconstruction, m, pairs, feats, match, seed)
        if points is None:  # A's own learned points: each view of A with its 3 nearest in viewing direction
            axes = {n: p[2, :3] for n, p in a_poses.items()}  # optical axes in A's frame
            inner = {tuple(sorted((a, b))) for a in axes
                     for b in sorted(axes, key=lambda b: -axes[a] @ axes[b])[1:4]}
            points = join.triangulated(result.reconstruction, sorted(inner), feats, match)
            row["a_pairs"], row["a_points"] = len(inner), len(points)
        near = {}
        for a, b in pairs:
            near.setdefault(b, []).append(a)
        k = join.decide(join.pnp_candidates(result.reconstruction, m, points, near, feats, match, seed), len(near),
                        centres=True)
        for how, got in (("pairs", j), ("pnp", k)):
            for c, cand in zip(got.candidates, got.found):
                if c["a"] != "pnp":
                    w2c = {n: np.linalg.inv(truth[n])[:3, :3] for n in (c["a"], c["b"])}
                    c["true_pair_deg"] = round(join.angle_deg(w2c[c["b"]] @ w2c[c["a"]].T), 1)  # views apart
                c["true_deg_off"] = round(join.angle_deg(cand.rotation @ q_true.T), 1)  # against the truth
            t[how] = {"accepted": got.accepted, "reason": got.reason, "consensus": got.consensus,
                      "candidates": got.candidates, "scale": got.scale}
            if got.accepted:
                joined[how].update(join.joined_poses(m, got))
        tries.append(t)
    row["join_cpu_seconds"] = round(time.process_time() - c1, 2)
    row["learned_images"], row["learned_pairs"] = len(feats), len(cache)
    row["tries"] = tries
    row["joined"] = {how: score(p, truth, extent) for how, p in joined.items()}
    row["load_1min_end"] = round(os.getloadavg()[0], 2)
    return row


def main(argv: list[str] | None = None) -> dict:
    parser = scene_parser(__doc__, ["blender/lego", "blender/chair"], "pose_join.json")
    parser.add_argument("--partners", type=int, default=3,
                        help="views of the kept model each view of another model is matched with (most similar by "
                             "SIFT words); 0 = all of them")
    args = parser.parse_args(argv)
    prov = start(args.threads, args.seed)
    from omnirecon.data.io import write_json

    rows = []
    for s in args.scenes:
        with tempfile.TemporaryDirectory(prefix="pose_join_") as tmp:
            rows.append(run(SHARED / s, args.images, Path(tmp), args.threads, args.seed, args.partners))
        print({k: v for k, v in rows[-1].items() if k != "tries"}, flush=True)
    prov["loadavg_1min_end"] = round(os.getloadavg()[0], 2)
    result = {"provenance": prov, "config": {"images_per_scene": args.images, "threads": args.threads,
                                             "partners": args.partners, "min_views": 3, "agree_deg": 5.0}, "scenes": rows}
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return result
