"""Pose recovery on a folder of real photos without true poses (lund): `omnirecon process` with its defaults,
scored by registered photos, reprojection error, seconds and CPU seconds, and by how its camera centres agree
with a posed copy of the same photos made earlier (another run's scene, not the truth).

    python -m bench poses --scenes --masked --photos photos/lund --reference PATH --threads 2 \\
        --out bench/results/poses_lund.json

Agreement: the recovered poses are aligned to the reference's by a similarity (rotation from the centres and
the cameras' axes, scale and shift from the centres: :func:`omnirecon.capture.align.pose_errors`); centre
errors are in % of the reference's extent (the largest distance between two of its camera centres). A walk's
photos are numbered in order, so consecutive photos stand about one step apart: where one model's step between
consecutive photos is over :data:`BREAK` times its median step, the walk is broken there (two pieces joined
wrongly), and the agreement is also given for each piece of the reference between its breaks.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

BREAK = 10.0
"""A step between consecutive photos over this many times the median step breaks the walk."""


def centres_and_c2w(scene: Path) -> tuple[list[str], np.ndarray]:
    """Photo names (sorted) and camera-to-world poses ``# [N, 4, 4]`` of the COLMAP model in ``scene/sparse/0``."""
    import pycolmap

    rec = pycolmap.Reconstruction(scene / "sparse" / "0")
    ims = sorted(rec.images.values(), key=lambda im: im.name)
    c2w = np.tile(np.eye(4), (len(ims), 1, 1))
    for k, im in enumerate(ims):
        c2w[k, :3] = im.cam_from_world().inverse().matrix()
    return [im.name for im in ims], c2w


def breaks(c2w: np.ndarray) -> list[int]:
    """Indices ``k`` where the step from photo ``k - 1`` to ``k`` is over :data:`BREAK` times the median step."""
    step = np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=1)  # [N - 1]
    return [int(k) + 1 for k in np.flatnonzero(step > BREAK * max(np.median(step), 1e-12))]


def agreement(est: np.ndarray, ref: np.ndarray) -> dict:
    """Rotation (degrees) and centre differences (% of the reference's extent) after the similarity alignment."""
    from omnirecon.capture.align import pose_errors

    extent = float(np.max(np.linalg.norm(ref[:, None, :3, 3] - ref[None, :, :3, 3], axis=-1)))
    e = pose_errors(est, ref, extent)
    return {k: round(e[k], 4) for k in ("rotation_deg_median", "rotation_deg_max", "centre_pct_median",
                                        "centre_pct_max")}


def compare(out: Path, reference: Path) -> dict:
    """The agreement of scene ``out`` with scene ``reference`` on the photos both pose, whole and per piece."""
    names_e, est = centres_and_c2w(out)
    names_r, ref = centres_and_c2w(reference)
    common = sorted(set(names_e) & set(names_r))
    est = est[[names_e.index(n) for n in common]]
    ref = ref[[names_r.index(n) for n in common]]
    cuts = breaks(ref)
    pieces = [(a, b) for a, b in zip([0, *cuts], [*cuts, len(common)]) if b - a >= 3]
    return {"common": len(common), **agreement(est, ref), "breaks_est": [common[k] for k in breaks(est)],
            "breaks_ref": [common[k] for k in cuts],
            "pieces": [{"from": common[a], "to": common[b - 1], **agreement(est[a:b], ref[a:b])}
                       for a, b in pieces] if cuts else []}


def run_photos(folder: Path, reference: Path | None, options, work: Path, shared: Path) -> dict:
    """``process`` on the photo folder ``folder`` with ``options``; a row like the scene rows of bench poses."""
    from bench.poses import cpu_now
    from omnirecon.capture.process import process
    from omnirecon.errors import InputError

    out = work / "scene"
    shutil.rmtree(out, ignore_errors=True)
    row = {"scene": f"{folder.name} (photos)", "path": str(folder.relative_to(shared)) if shared in folder.parents
           else str(folder), "images": len([p for p in folder.iterdir() if p.suffix.lower() in {".jpg", ".jpeg", ".png"}]),
           "method": "sift", "load_1min_start": round(os.getloadavg()[0], 2)}
    options = replace(options, learned="off")
    t0, c0 = time.perf_counter(), cpu_now()
    try:
        s = process(folder, out, options, quiet=True)
    except InputError as e:
        row.update(error=e.one_line(), registered=0, seconds=round(time.perf_counter() - t0, 2),
                   cpu_seconds=round(cpu_now() - c0, 2))
        return row
    row.update(seconds=round(time.perf_counter() - t0, 2), cpu_seconds=round(cpu_now() - c0, 2),
               load_1min_end=round(os.getloadavg()[0], 2), registered=s["images_registered"],
               reprojection_px=round(s["mean_reprojection_error_px"], 4), points3D=s["points3D"],
               matcher=s["matcher"], pairs=s["pairs"], stage_seconds=s["seconds"], stage_cpu=s.get("cpu_seconds"),
               attempts=s["attempts"],
               size=s.get("image_size"), options=s.get("options"))
    if reference is not None:
        row["reference"] = str(reference)
        row["agreement"] = compare(out, reference)
        made = reference / "process.json"
        if made.is_file():  # how the reference was made: its own summary
            r = json.loads(made.read_text())
            row["reference_run"] = {k: r.get(k) for k in ("images_registered", "mean_reprojection_error_px",
                                                          "matcher", "pairs", "seconds", "options")}
    return row
