"""Photos or a video in, a posed COLMAP scene out (what ``omnirecon process`` runs).

Everything is built in a hidden temporary folder beside ``out`` (``.<name>.tmp<pid>``) and swapped in
at the very end (:func:`omnirecon.outputs.claim`: one run per ``out``, never inside or around the
photos, ``overwrite`` replaces only a scene this tool wrote), so a failure or Ctrl-C leaves the
previous folder or none. The scene holds

    images/            undistorted photos (PINHOLE cameras), at full size
    images_2/, images_4/   the same, downscaled by 2 and 4 (area averaging)
    masks/, masks_2/, masks_4/   with ``masks``: the object masks, undistorted and downscaled like the
                       photos (:mod:`omnirecon.capture.masks`), so every command reads them as the scene's
    sparse/0/          cameras.bin, images.bin, points3D.bin: the largest model COLMAP found
    process.json       the summary: images registered / given, reprojection error, points, seconds per stage
                       (wall, and CPU seconds of the SfM process: ``cpu_seconds``)

Photos with a side under :data:`MIN_SIDE` pixels are refused before SfM, and the pycolmap stages (features,
matching, mapping, undistortion) run in a child process (:func:`sfm_in_child`), so a native crash of the
library (a segmentation fault or an abort) is one error line naming the input, not the end of the command;
the work folder and the lock go as after any failure.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import signal
import time
from dataclasses import asdict
from pathlib import Path

from omnirecon.capture.colmap_sfm import MIN_MATCHES, SfmOptions, Stages, run_sfm, write_scene
from omnirecon.capture.images import MIN_SIDE, VIDEO_EXTS, check_sizes, count_files, stage_images, stage_masks
from omnirecon.capture.learned import DETECTOR, label
from omnirecon.capture.video import clip_rate
from omnirecon.capture.video_sfm import video_sfm
from omnirecon.data.photo import regular_file
from omnirecon.errors import InputError
from omnirecon.outputs import claim


def process(source: Path, out: Path, options: SfmOptions | None = None, fps: float = 2.0, max_frames: int = 300,
            overwrite: bool = False, quiet: bool = False, keep_work: bool = False, masks: Path | None = None,
            claimed: bool = False) -> dict:
    """Run structure from motion on the photos in folder ``source`` (or the frames of video ``source``)
    and write the scene ``out``. ``masks``: a folder of masks matched to the photos by name; features
    are detected only inside them (objects on a turntable), and the scene keeps them as its object masks. Returns the summary that is also saved
    as ``out/process.json``. ``claimed``: the caller holds the claim of a folder ``out`` lies in (``reconstruct``'s
    work folder), so ``out`` (absent) is written in place instead of claimed."""
    options = options or SfmOptions()
    options.check()
    source, out = Path(source), Path(out)
    if not source.exists():
        raise InputError("input does not exist", source, "pass a folder of photos or a video file")
    if not source.is_dir():
        regular_file(source, "input", "pass a folder of photos or a video file")  # a FIFO or device blocks
    is_video = source.is_file()
    if is_video and source.suffix.lower() not in VIDEO_EXTS:
        raise InputError(f"not a folder or a video ({source.suffix or 'no extension'})", source,
                         f"pass a folder of photos, or a video ({', '.join(VIDEO_EXTS)})")
    t0 = time.perf_counter()
    if claimed:
        shutil.rmtree(out, ignore_errors=True)  # the caller's folder: a scene a cut-off run half wrote goes
        out.mkdir()  # _build takes an empty folder
        return _build(source, out, options, fps, max_frames, quiet, keep_work, masks, is_video, t0)
    with claim(out, "process", inputs=(source, masks), mode="replace", overwrite=overwrite) as owned:
        return _build(source, owned.work, options, fps, max_frames, quiet, keep_work, masks, is_video, t0)


def _build(source: Path, scene: Path, options: SfmOptions, fps: float, max_frames: int, quiet: bool,
           keep_work: bool, masks: Path | None, is_video: bool, t0: float) -> dict:
    """Structure from motion into the (temporary, empty) scene folder ``scene``; returns the summary."""
    work = scene.parent / f"{scene.name}.work"  # .OUT.tmpPID.work: a stale temporary if the run is killed
    scene.rmdir()  # write_scene creates it
    try:
        with Stages(quiet) as stages:
            objects, mask_dir, rotated = None if masks is None else work / "objects", None, None
            if is_video:  # frames are sampled in the SfM process too: video_sfm's passes sample and map in turn
                fps = sample_rate(source, fps, say=None if quiet else print)
                job = (None, None, work, options, True, source, masks, scene, objects, quiet, (fps, max_frames))
            else:
                with stages.stage("check", count_files(source)) as advance:
                    staged = stage_images(source, work / "input", min_images=3,
                                          shared_camera=not options.per_image_cameras, on_file=advance)
                check_sizes(staged)
                mask_dir = None if masks is None else stage_masks(masks, staged, work / "masks",
                                                                  options.mask_dilate, objects=objects)
                rotated = staged.rotated
                job = (staged.folder, staged.names, work, options, False, source, mask_dir, scene, objects, quiet, None)
            seconds = dict(stages.seconds)
        child_cpu = CHILD_CPU_SECONDS[0]
        stats, info, sfm_seconds, video = sfm_in_child(source, job)
        seconds.update(sfm_seconds)
        summary = {
            "input": str(source), "kind": "video" if is_video else "images", **stats,
            "image_size": info["size"], "cropped_to_common_size": info["crop"],
            "exif_rotated": video["rotated"] if is_video else rotated,
            "options": asdict(options), "masks": None if masks is None else str(masks),
            **({"fps": video["passes"][-1]["fps"], "video_passes": video["passes"]} if is_video else {}),
            "seconds": {**seconds, "total": round(time.perf_counter() - t0, 3)},
            "sfm_cpu_seconds": round(CHILD_CPU_SECONDS[0] - child_cpu, 2),
        }
        (scene / "process.json").write_text(json.dumps(summary, indent=1))
        if keep_work:
            shutil.move(str(work), str(scene / "colmap_work"))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return summary


def sample_rate(video: Path, fps: float, say=print) -> float:
    """The rate to sample ``video`` at for ``--fps fps``: at most the clip's own frame rate (above it ffmpeg
    repeats frames; ``say`` is told), and refused when it samples less than one frame of the clip."""
    rate, seconds = clip_rate(video)
    frames = round(rate * seconds) if rate and seconds else None
    if frames is not None and frames < 3:  # no --fps gives the 3 views a pose needs
        raise InputError(f"the clip holds {frames} frame{'s' * (frames != 1)} ({seconds:.2g} s): too short to pose",
                         video, "record a clip of several seconds, walking slowly around the subject")
    if seconds is not None and fps * seconds < 1:
        raise InputError(f"--fps {fps:g} samples no frame from a {seconds:.1f} s clip", None,
                         f"use --fps of at least {1 / seconds:.3g}, e.g. --fps {min(rate or 1e9, max(2.0, 3 / seconds)):.3g}")
    if rate is not None and fps > rate:
        if say is not None:
            say(f"note: --fps {fps:g} is above the clip's own {rate:g} frames per second: sampling every frame "
                f"({rate:g} per second) instead of repeating frames")
        return rate
    return fps


def _sfm(args: tuple) -> tuple[dict, dict, dict, dict | None]:
    """The pycolmap stages (what the child of :func:`sfm_in_child` runs): on staged photos, or on a video's frames
    (``video = (fps, max_frames)``: :func:`omnirecon.capture.video_sfm.video_sfm` samples and maps, denser when too
    few register; ``mask_dir`` is then the user's masks folder). Returns ``(the result's stats, the scene's info,
    seconds per stage, the video's passes and EXIF rotations or None)``."""
    folder, names, work, options, is_video, source, mask_dir, scene, objects, quiet, video = args
    with Stages(quiet) as stages:
        if video is not None:
            result, staged, passes, kept = video_sfm(source, work, options, video[0], video[1], stages, mask_dir)
            folder, objects = staged.folder, None if mask_dir is None else kept / "objects"
            video = {"passes": passes, "rotated": staged.rotated}
        else:
            result = run_sfm(folder, names, work, options, stages, video=is_video, source=source, mask_dir=mask_dir)
        info = write_scene(result, folder, work, scene, stages, threads=options.threads, masks=objects)
    return {**result.stats(), "cpu_seconds": dict(stages.cpu)}, info, dict(stages.seconds), video


def _die_with(parent: int) -> None:
    """End this process when the command ``parent`` ends, even by SIGKILL (Linux ``prctl(PR_SET_PDEATHSIG)``;
    elsewhere nothing): a killed command leaves no SfM child writing into its work folder. The signal comes when
    this process's own parent ends: multiprocessing's fork server, which exits when the command does (its pipe from
    the command closes); a command already gone is checked for after the request."""
    import ctypes

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    from multiprocessing import forkserver

    server = getattr(forkserver, "_forkserver", None)
    alive = getattr(server, "_forkserver_alive_fd", None)
    if alive is not None:  # the server's end of its pipe from the command, handed to each child: while a child
        try:               # held it, the server never saw the command end (nor did the child)
            os.close(alive)
        except OSError:
            pass
        server._forkserver_alive_fd = None
    try:
        os.kill(parent, 0)  # the command ended before the request took effect
    except ProcessLookupError:
        os._exit(1)


PRELOAD = ["omnirecon.capture.sfm_server", "omnirecon.capture.process", "pycolmap"]
"""What the fork server imports once, before the SfM children fork from it (a spawned child imported torch and
pycolmap again: ~2 CPU-s per ``process`` call); :mod:`omnirecon.capture.sfm_server` ties the server to the command."""


def _sfm_context():
    """multiprocessing's ``forkserver`` context with :data:`PRELOAD`: each child is a fork of a clean server process
    (no thread of the command's torch or GUI state in it), started in milliseconds; ``spawn`` where there is no fork
    server (Windows)."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(PRELOAD)
    return ctx


CHILD_CPU_SECONDS = [0.0]
"""CPU seconds (every thread) of the SfM children this process has run (:func:`sfm_in_child`): a child's CPU is not
the process's own (``time.process_time``), so the stage clocks add this (``reconstruct``'s ``Laps``)."""


def _sfm_child(conn, args: tuple, parent: int) -> None:
    _die_with(parent)
    try:
        out = ("done", (_sfm(args), time.process_time()))
    except InputError as e:
        out = ("input", (e.what, e.path, e.fix))
    except BaseException as e:  # noqa: BLE001 - sent to the parent, which raises it
        import traceback

        out = ("other", (type(e).__name__, str(e), traceback.format_exc()))
    conn.send(out)
    conn.close()


def sfm_in_child(source: Path, args: tuple) -> tuple[dict, dict, dict, dict | None]:
    """:func:`_sfm` in a child process (:func:`_sfm_context`): its InputError is raised here as it was; a native
    crash (the child killed by a signal) becomes an InputError naming ``source``; another exception a RuntimeError
    carrying the child's traceback."""
    ctx = _sfm_context()
    receive, send = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_sfm_child, args=(send, args, os.getpid()), name="omnirecon-sfm", daemon=True)
    child.start()
    send.close()
    try:
        try:
            kind, payload = receive.recv()
        except EOFError:  # the child died without an answer
            kind, payload = "crash", None
        child.join()
    finally:
        if child.is_alive():  # Ctrl-C or an error here: the child goes with the command
            child.kill()
            child.join()
        receive.close()
    if kind == "done":
        result, cpu = payload
        CHILD_CPU_SECONDS[0] += cpu
        return result
    if kind == "input":
        raise InputError(*payload)
    if kind == "other":
        if payload[0] == "KeyboardInterrupt":
            raise KeyboardInterrupt
        raise RuntimeError(f"{payload[0]} in the SfM process: {payload[1]}\n{payload[2]}")
    code = child.exitcode
    how = signal.Signals(-code).name if code is not None and code < 0 and -code in signal.Signals._value2member_map_ \
        else f"exit {code}"
    raise InputError(f"the SfM library (pycolmap) crashed ({how}) on these photos", source,
                     f"check that the photos are sharp, overlap and are at least {MIN_SIDE} px a side; "
                     "a different set or --per-image-cameras may get past it")


def motion_lines(s: dict) -> list[str]:
    """The turntable hint of a :func:`process` summary (``motions``): empty unless the check found a still
    background behind a turning object and no masks were given."""
    m = s.get("motions") or {}
    if not m.get("turntable") or s.get("masks"):
        return []
    return [f"note: a turntable capture? In photos posed {m.get('min_turn', 10):g}+ degrees apart, {m['share']:.0%} of "
            "the matches (median) move together as one piece: a still background behind an object that turns. The "
            "poses cannot fit both; pass --masks DIR (one mask per photo, named like it, white on the object) so "
            "they follow the object, or walk around the object instead of turning it"]


def summary_lines(s: dict) -> list[str]:
    """Human-readable lines of a :func:`process` summary."""
    sec = s["seconds"]
    lines = [
        f"registered {s['images_registered']} / {s['images_given']} images; {s['points3D']} 3-D points; "
        f"mean reprojection error {s['mean_reprojection_error_px']:.3f} px; {s['matcher']} matching "
        f"({s['pairs']} pairs); undistorted to PINHOLE at {s['image_size'][0]}x{s['image_size'][1]}",
        "seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in sec.items()),
    ]
    if s["models"] > 1:
        lines.append(f"note: COLMAP found {s['models']} separate models; kept the largest "
                     f"({s['images_registered']} images)")
    retried = s.get("attempts", [])[1:]
    if retried:
        kept = next((a["attempt"] for a in s["attempts"] if a.get("kept")), "")
        lines.append(f"retried the mapping {len(retried)} times ({s['attempts'][0]['registered']} images at first); "
                     f"kept: {kept}")
    if s["unregistered"]:
        d = s.get("dropped") or [{"name": n, "reason": ""} for n in s["unregistered"]]
        shown = "; ".join(f"{x['name']} ({x['reason']})" if x["reason"] else x["name"] for x in d[:10])
        lines.append(f"dropped {len(d)} photos (no pose): " + shown + (" ..." if len(d) > 10 else ""))
        reach = s.get("reachable", s["images_given"])
        if reach < s["images_given"]:
            lines.append(f"{s['images_given'] - reach} of the photos share no pair of {MIN_MATCHES}+ verified matches with the "
                         f"posed ones: with these features at most {reach} of {s['images_given']} can get a pose "
                         "(add photos between those views and the rest)")
    passes = s.get("video_passes") or []
    if len(passes) > 1:
        lines.append(f"video: {passes[0]['registered']} of {passes[0]['frames']} frames registered at "
                     f"{passes[0]['fps']:g} fps; sampled again at {passes[1]['fps']:g} fps and matched in sequence "
                     "with loop detection (kept)")
    learned = s.get("learned") or {}
    if learned.get("status") == "used":
        lines.append(f"learned matches ({label(learned.get('detector', DETECTOR))}) for the {learned['unplaced']} photos SIFT left out: "
                     f"{learned['pairs']} pairs of {learned['images']} photos, {learned['verified_pairs']} verified")
    elif learned.get("status") == "not installed" and s["unregistered"]:
        lines.append(f"more photos may get a pose with the learned matcher: {learned['install']}")
    checked = (s.get("pose_check") or {}).get("dropped") or []
    if checked:
        lines.append(f"pose check: dropped {len(checked)} poses that contradict their verified matches ("
                     f"{', '.join(checked[:6])}{' ...' if len(checked) > 6 else ''}): no pose is better than a wrong "
                     "one; --min-explained 0 keeps them")
    if s.get("masks"):
        lines.append("object masks kept in masks/ (undistorted like the photos): mesh --masks, reconstruct and finetune's "
                     "object scores use them")
    lines += motion_lines(s)
    if s.get("exif_rotated"):
        lines.append(f"{s['exif_rotated']} photos turned upright by their EXIF orientation")
    return lines
