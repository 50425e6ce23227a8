"""Pose recovery: `omnirecon process` on the real scenes with their poses thrown away.

    python -m bench poses                    # 7 real scenes, 20 images each at their stored size, 1 thread
    python -m bench poses --tiny             # one procedural scene (for tests)
    python -m bench poses --scenes blender/lego --masked --methods sift hybrid --out bench/results/poses_hybrid.json
    python -m bench poses --scenes --masked --videos instant_ngp/fox --out bench/results/poses_video.json
    python -m bench poses --scenes --masked --photos photos/lund --reference SCENE --threads 2 --out bench/results/poses_lund.json

``--methods``: ``sift`` is SIFT alone (``SfmOptions.learned = "off"``); ``hybrid`` adds learned matches
(DISK + LightGlue) for the views SIFT left out (``learned = "auto"``, needs the ``capture-learned`` extra);
``learned`` keeps that model whenever it poses more views (``learned = "prefer"``).
Each row also carries the pose check's summary (views dropped as contradicting their matches).

``--photos``: photo folders without poses (lund's 29 street photos), with ``process``'s own defaults, compared
with a posed ``--reference`` copy of them (:mod:`bench.poses_photos`).

``--videos``: a phone walk-around clip made from a scene's frames in capture order (fox: one loop around
the subject), every frame once, resized to ``--video-size`` pixels on the long side and spread over
``--video-seconds`` (fox: 67 frames, 136x240, 40 s), given to ``process`` as a video at its default
``--fps 2``. Each registered frame is matched to its source frame by pixel difference, then scored as above.

For each scene, ``--images`` views are taken evenly spaced over its views (the ``train`` split where
the scene has one), their image files (only) are handed to :func:`omnirecon.capture.process.process`,
and the recovered cameras are compared with the scene's own poses after a similarity (Umeyama)
alignment of the camera centres: registered fraction, rotation error (degrees), camera-centre error
(% of the scene extent = the diagonal of the reference scene's bounds box, as its reader gives it) and
seconds. Writes JSON with a provenance header to ``--out``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
SCENES = ("blender/lego", "blender/chair", "instant_ngp/fox", "llff/fern", "llff/ethiopianHead",
          "neus_dtu/dtu_scan24", "neus_dtu/dtu_scan37")
MASKED = ("llff/ethiopianHead",)  # a turntable: the background stays still while the object turns
GOALS = {"registered": 0.95, "rotation_deg_median": 1.0, "centre_pct_median": 1.0, "seconds_20": 60.0}


def pick_views(scene, count: int, split: str = "train") -> list[int]:
    """``count`` view indices evenly spaced over the ``split`` views (all views when it has none)."""
    pool = scene.splits.get(split) or scene.splits["all"]
    if len(pool) <= count:
        return list(pool)
    return [pool[i] for i in np.unique(np.linspace(0, len(pool) - 1, count).round().astype(int))]


def scene_parser(doc: str, scenes: list[str], out: str) -> argparse.ArgumentParser:
    """The arguments the pose experiments share: --scenes (default ``scenes``), --images, --threads, --seed and
    --out (default ``bench/results/<out>``); each experiment adds its own."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=list(scenes), help="paths under the shared data folder")
    parser.add_argument("--images", type=int, default=20, help="views per scene (evenly spaced over the train split)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / out)
    return parser


def start(threads: int, seed: int) -> dict:
    """Set this process's torch / OpenMP threads and return the run's provenance (with pycolmap's version),
    taken at the start."""
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    import pycolmap
    import torch

    from omnirecon.provenance import provenance

    torch.set_num_threads(threads)
    return provenance(seed=seed, pycolmap=pycolmap.__version__, colmap_threads=threads)


def cpu_now() -> float:
    """CPU seconds of this process and of its children that have ended (``process`` maps in a child process)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def run_scene(path: Path, count: int, options, work: Path, split: str = "train", masks: bool = False,
              method: str = "sift") -> dict:
    from omnirecon.capture.align import pose_errors
    from omnirecon.capture.process import process
    from omnirecon.data import load_scene
    from omnirecon.errors import InputError

    ref = load_scene(path)
    views = pick_views(ref, count, split)
    folder = work / "photos"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    names = {}
    mask_dir = work / "masks"
    shutil.rmtree(mask_dir, ignore_errors=True)
    if masks:
        if ref.masks is None:
            raise SystemExit(f"{path} has no masks")
        mask_dir.mkdir(parents=True)
    for i in views:
        src = Path(ref.path) / ref.names[i]
        name = src.name
        if name in names:  # same file name in two split folders
            name = f"{src.parent.name}_{src.name}"
        shutil.copyfile(src, folder / name)
        names[name] = i
        if masks:  # the reader's mask at the stored size (LLFF masks_<N> matched by stem)
            Image.fromarray(ref.masks[i].numpy().astype(np.uint8) * 255).save(mask_dir / f"{Path(name).stem}.png")
    out = work / "scene"
    shutil.rmtree(out, ignore_errors=True)
    row = {"scene": path.name, "path": str(path.relative_to(SHARED)) if SHARED in path.parents else str(path),
           "images": len(views), "size": [ref.width, ref.height], "rig": ref.rig, "masks": masks, "method": method,
           "load_1min_start": round(os.getloadavg()[0], 2)}
    options = replace(options, learned={"sift": "off", "hybrid": "auto", "learned": "prefer"}[method])
    t0, c0 = time.perf_counter(), cpu_now()  # CPU seconds of this process and its finished children (the SfM child)
    try:
        summary = process(folder, out, options, quiet=True, masks=mask_dir if masks else None)
    except InputError as e:
        row.update(error=e.one_line(), registered=0, registered_fraction=0.0,
                   seconds=round(time.perf_counter() - t0, 2), cpu_seconds=round(cpu_now() - c0, 2))
        return row
    row["seconds"] = round(time.perf_counter() - t0, 2)
    row["cpu_seconds"] = round(cpu_now() - c0, 2)
    est = load_scene(out)
    c2w_est = est.cameras.transformed(est.to_input).c2w.numpy()  # in COLMAP's own frame
    idx = [names[Path(n).name] for n in est.names]
    extent = float((ref.bounds[1] - ref.bounds[0]).double().norm())
    err = pose_errors(c2w_est, ref.cameras.c2w[idx].numpy(), extent)
    row.update(
        registered=len(idx), registered_fraction=round(len(idx) / len(views), 4),
        rotation_deg_median=round(err["rotation_deg_median"], 4), rotation_deg_mean=round(err["rotation_deg_mean"], 4),
        rotation_deg_max=round(err["rotation_deg_max"], 4),
        centre_pct_median=round(err["centre_pct_median"], 4), centre_pct_mean=round(err["centre_pct_mean"], 4),
        centre_pct_max=round(err["centre_pct_max"], 4), extent=round(extent, 5),
        points3D=summary["points3D"], reprojection_px=round(summary["mean_reprojection_error_px"], 4),
        models=summary["models"], matcher=summary["matcher"], stage_seconds=summary["seconds"],
        dropped=summary.get("dropped", []), attempts=summary.get("attempts", []), reachable=summary.get("reachable"),
        detected_rig=est.rig, focal_est=round(float(est.cameras.fx[0]), 2), focal_ref=round(float(ref.cameras.fx[0]), 2),
        pose_check=summary.get("pose_check"), learned=summary.get("learned"),
    )
    return row


def make_clip(ref, dest: Path, long_side: int, seconds: float) -> tuple[Path, np.ndarray, list[int]]:
    """An H.264 clip of every view of ``ref`` in name order at ``long_side`` pixels (even sides), the whole set over
    ``seconds``; returns its path, the frames ``# [N, H, W, 3]`` uint8 and their view indices (clip order)."""
    import imageio_ffmpeg

    order = sorted(range(len(ref)), key=lambda i: ref.names[i])
    w, h = ref.width, ref.height
    s = long_side / max(w, h)
    size = (2 * round(w * s / 2), 2 * round(h * s / 2))
    frames = np.stack([np.asarray(Image.open(Path(ref.path) / ref.names[i]).convert("RGB").resize(size, Image.LANCZOS))
                       for i in order])
    dest.parent.mkdir(parents=True, exist_ok=True)
    writer = imageio_ffmpeg.write_frames(str(dest), size, fps=len(order) / seconds, quality=8, macro_block_size=2)
    writer.send(None)
    for f in frames:
        writer.send(np.ascontiguousarray(f))
    writer.close()
    return dest, frames, order


def run_video(path: Path, long_side: int, seconds: float, options, work: Path, method: str = "sift") -> dict:
    """:func:`make_clip` of scene ``path`` given to ``process``; the row of :func:`run_scene`'s shape."""
    from omnirecon.capture.align import pose_errors
    from omnirecon.capture.process import process
    from omnirecon.data import load_scene
    from omnirecon.errors import InputError

    ref = load_scene(path)
    clip, frames, order = make_clip(ref, work / "clip.mp4", long_side, seconds)
    out = work / "scene"
    shutil.rmtree(out, ignore_errors=True)
    row = {"scene": f"{path.name} (video)", "path": str(path.relative_to(SHARED)) if SHARED in path.parents else str(path),
           "images": len(order), "size": [int(frames.shape[2]), int(frames.shape[1])], "seconds_clip": seconds,
           "rig": ref.rig, "masks": False, "method": method, "load_1min_start": round(os.getloadavg()[0], 2)}
    options = replace(options, learned={"sift": "off", "hybrid": "auto", "learned": "prefer"}[method])
    t0 = time.perf_counter()
    try:
        summary = process(clip, out, options, quiet=True)
    except InputError as e:
        row.update(error=e.one_line(), registered=0, registered_fraction=0.0, seconds=round(time.perf_counter() - t0, 2))
        return row
    row["seconds"] = round(time.perf_counter() - t0, 2)
    est = load_scene(out)
    small = frames.reshape(len(frames), -1).astype(np.float32)  # [N, H*W*3]
    idx = []
    for n in est.names:  # the clip frame each registered frame was sampled from
        a = np.asarray(Image.open(Path(est.path) / n).convert("RGB").resize((frames.shape[2], frames.shape[1])),
                       np.float32).reshape(1, -1)
        idx.append(order[int(np.argmin(((small - a) ** 2).mean(1)))])
    c2w_est = est.cameras.transformed(est.to_input).c2w.numpy()
    extent = float((ref.bounds[1] - ref.bounds[0]).double().norm())
    err = pose_errors(c2w_est, ref.cameras.c2w[idx].numpy(), extent)
    sampled = sum(p["frames"] for p in summary["video_passes"][-1:])
    row.update(registered=len(idx), sampled=sampled, registered_fraction=round(len(idx) / max(sampled, 1), 4),
               distinct_views=len(set(idx)), video_passes=summary["video_passes"],
               rotation_deg_median=round(err["rotation_deg_median"], 4), rotation_deg_max=round(err["rotation_deg_max"], 4),
               centre_pct_median=round(err["centre_pct_median"], 4), centre_pct_max=round(err["centre_pct_max"], 4),
               extent=round(extent, 5), reprojection_px=round(summary["mean_reprojection_error_px"], 4),
               stage_seconds=summary["seconds"], pose_check=summary.get("pose_check"))
    return row


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=list(SCENES), help="paths under the shared data folder")
    parser.add_argument("--masked", nargs="*", default=list(MASKED),
                        help="scenes also run with their masks given to process (turntable captures)")
    parser.add_argument("--images", type=int, default=20, help="images per scene (evenly spaced)")
    parser.add_argument("--split", default="train", help="the scene split the images are taken from (all: every view)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--camera-model", default="SIMPLE_RADIAL")
    parser.add_argument("--affine-sift", action="store_true")
    parser.add_argument("--no-guided", action="store_true")
    parser.add_argument("--peak-threshold", type=float, default=0.0067)
    parser.add_argument("--retry-below", type=float, default=1.0, help="0 = the mapping is never retried")
    parser.add_argument("--mask-dilate", type=int, default=0, help="pixels the masks grow by (masked scenes only)")
    parser.add_argument("--jobs", type=int, default=1, help="scenes run side by side in this many processes")
    parser.add_argument("--tiny", action="store_true", help="one 12-view procedural scene instead of the real ones")
    parser.add_argument("--methods", nargs="+", default=["sift"], choices=["sift", "hybrid", "learned"],
                        help="sift: SIFT alone; hybrid: plus learned matches where SIFT fails, kept under the retry "
                             "rule; learned: the learned model kept whenever it poses more (capture-learned extra)")
    parser.add_argument("--videos", nargs="*", default=[], help="scenes also run as a walk-around video clip")
    parser.add_argument("--video-size", type=int, default=240, help="the clip's long side (pixels)")
    parser.add_argument("--video-seconds", type=float, default=40.0, help="the clip's length (seconds)")
    parser.add_argument("--photos", nargs="*", default=[], help="photo folders without poses (paths under the shared "
                        "data folder, e.g. photos/lund) run through process with its own defaults (bench/poses_photos.py)")
    parser.add_argument("--reference", type=Path, default=None,
                        help="a posed scene of the same photos whose camera centres the --photos rows are compared with")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "poses.json")
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    import torch

    from omnirecon.data.io import write_json
    from omnirecon.provenance import provenance

    torch.set_num_threads(args.threads)
    import pycolmap

    prov = provenance(seed=args.seed, pycolmap=pycolmap.__version__, colmap_threads=args.threads)  # at the start
    from omnirecon.capture.colmap_sfm import SfmOptions

    options = SfmOptions(camera_model=args.camera_model, threads=args.threads, seed=args.seed, min_registered=0.0, affine_sift=args.affine_sift,
                         guided_matching=not args.no_guided, peak_threshold=args.peak_threshold,
                         retry_below=args.retry_below)
    rows = []
    with tempfile.TemporaryDirectory(prefix="poses_") as tmp:
        tmp = Path(tmp)
        if args.tiny:
            from omnirecon.data.synth.generate import SynthOptions, generate_scene

            paths = [generate_scene(tmp / "synth", 0, SynthOptions(rig="frontal", views=12, resolution=256))]
        else:
            paths = [SHARED / s for s in args.scenes if (SHARED / s).is_dir()]
        jobs = [(p, False) for p in paths]
        if not args.tiny:
            jobs += [(SHARED / s, True) for s in args.masked if (SHARED / s).is_dir()]
        jobs = [(p, masked, m) for p, masked in jobs for m in args.methods]
        videos = [(SHARED / s, m) for s in args.videos if (SHARED / s).is_dir() for m in args.methods]
        calls = [(p, args.images, replace(options, mask_dilate=args.mask_dilate) if masked else options,
                  tmp / f"work{k}", "all" if args.tiny else args.split, masked, m)
                 for k, (p, masked, m) in enumerate(jobs)]
        if args.jobs > 1:  # scenes side by side, each in its own process at --threads (rows keep their order)
            from concurrent.futures import ProcessPoolExecutor

            with ProcessPoolExecutor(args.jobs) as pool:
                rows = list(pool.map(run_scene, *zip(*calls)))
        else:
            rows = []
            for c in calls:
                rows.append(run_scene(*c))
                print({k: v for k, v in rows[-1].items() if k not in ("stage_seconds", "attempts", "dropped")},
                      flush=True)
        for k, p in enumerate(SHARED / s for s in args.photos):  # the process defaults, at --threads
            from bench.poses_photos import run_photos

            rows.append(run_photos(p, args.reference, SfmOptions(threads=args.threads, seed=args.seed, min_registered=0.0),
                                   tmp / f"photos{k}", SHARED))
            print({k: v for k, v in rows[-1].items() if k not in ("stage_seconds", "attempts", "options")}, flush=True)
        for k, (p, m) in enumerate(videos):
            rows.append(run_video(p, args.video_size, args.video_seconds, options, tmp / f"video{k}", m))
            print({k: v for k, v in rows[-1].items() if k not in ("stage_seconds", "video_passes")}, flush=True)
    prov["loadavg_1min_end"] = round(os.getloadavg()[0], 2)
    result = {
        "provenance": prov,
        "config": {"images_per_scene": args.images, "split": args.split, "threads": args.threads, "jobs": args.jobs, "tiny": args.tiny,
                   "videos": {"scenes": args.videos, "long_side": args.video_size, "seconds": args.video_seconds},
                   "photos": {"folders": args.photos, "reference": None if args.reference is None else str(args.reference),
                              "sfm_options": asdict(SfmOptions(threads=args.threads, seed=args.seed, min_registered=0.0))},
                   "methods": args.methods,
                   "size": "each scene's stored image size (long side <= 400 px)",
                   "camera_model": f"{args.camera_model}, one shared camera", "sfm_options": asdict(options),
                   "mask_dilate_masked_scenes": args.mask_dilate, "alignment": "Umeyama similarity on camera centres",
                   "extent": "diagonal of the reference scene's bounds box"},
        "goals": GOALS,
        "scenes": rows,
    }
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return result

