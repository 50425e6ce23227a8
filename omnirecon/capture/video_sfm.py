"""Poses from a video: the user cannot add photos, but the tool can take more frames.

:func:`video_sfm` samples the video at ``fps`` and runs structure from motion on the frames (sequential
matching). When too few frames register, it samples again :data:`DENSER` times as densely (within
``max_frames`` over the whole clip) and matches in sequence plus loop pairs found by retrieval
(:mod:`omnirecon.capture.retrieval`: a walk around a subject returns to its start). Learned matches
(:attr:`SfmOptions.learned`) are tried only in the last pass: more frames cost less. When that fails
too, the error names both passes and what the user can do: a slower walk, more light, ``--fps``.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from omnirecon.capture.colmap_sfm import SfmOptions, SfmResult, Stages, needed, run_sfm
from omnirecon.capture.images import StagedImages, check_sizes, stage_images, stage_masks
from omnirecon.capture.video import clip_rate, sample_frames
from omnirecon.errors import InputError

DENSER = 3.0
"""The second pass samples the video at this many times the first pass's frames per second."""
LOOP_PAIRS = 5
"""Loop pairs per frame in the second pass (:attr:`SfmOptions.loop_pairs`)."""


def video_pass(source: Path, work: Path, options: SfmOptions, fps: float, max_frames: int, stages: Stages,
               masks: Path | None = None) -> tuple[SfmResult | None, StagedImages, dict]:
    """Frames at ``fps`` (at most ``max_frames``) into ``work`` and their structure from motion (``masks``:
    a folder of masks named like the frames, ``frame_00000.png``, ...; staged as object masks into
    ``work/objects``); returns the result (None when no model came out), the staged frames and a record."""
    suffix = "" if work.name == "pass0" else f" ({fps:g} fps)"
    with stages.stage(f"frames{suffix}", None) as advance:
        names = sample_frames(source, work / "frames_raw", fps, max_frames, on_frame=lambda i, e: advance(1, e))
    if len(names) < 3:  # a frames folder is no photo folder: say it in the clip's terms
        raise InputError(f"--fps {fps:g} samples {len(names)} frame{'s' * (len(names) != 1)} of the clip; structure "
                         "from motion needs at least 3", source, "raise --fps, or record a longer clip walking "
                         "slowly around the subject")
    staged = stage_images(work / "frames_raw", work / "input", min_images=3, shared_camera=True)
    check_sizes(staged, source)  # before SfM: frames too small crash it
    mask_dir = None if masks is None else stage_masks(masks, staged, work / "masks", options.mask_dilate,
                                                      objects=work / "objects")
    record = {"fps": round(fps, 4), "frames": len(staged.names), "loop_pairs": options.loop_pairs, "registered": 0}
    try:
        result = run_sfm(staged.folder, staged.names, work, replace(options, min_registered=0.0), stages, video=True,
                         source=source, mask_dir=mask_dir)
    except InputError as e:
        record["error"] = e.what
        return None, staged, record
    record["registered"] = len(result.registered)
    return result, staged, record


def video_sfm(source: Path, work: Path, options: SfmOptions, fps: float, max_frames: int, stages: Stages,
              masks: Path | None = None) -> tuple[SfmResult, StagedImages, list[dict], Path]:
    """Structure from motion on the frames of video ``source`` (see the module's note; ``masks`` as in
    :func:`video_pass`); returns the kept pass's result, frames, the record of every pass and the kept
    pass's folder (its ``objects/``: the staged object masks). Raises :class:`InputError` naming what was tried
    when neither pass registers :attr:`SfmOptions.min_registered` of its frames."""
    rate, duration = clip_rate(source)
    dense = min(fps * DENSER, max_frames / duration if duration else fps * DENSER, rate or fps * DENSER)
    more = dense > 1.2 * fps  # room for a denser pass: the first one uses SIFT alone (more frames cost less)
    limit = "every frame of the clip was sampled" if rate and dense >= rate else \
        f"--max-frames {max_frames} leaves no room to sample more densely"
    result, staged, first = video_pass(source, work / "pass0", replace(options, learned="off") if more else options,
                                       fps, max_frames, stages, masks)
    passes = [first]
    if first["registered"] >= needed(options.min_registered, first["frames"]):
        return result, staged, passes, work / "pass0"
    if more:
        denser = replace(options, matcher="sequential", loop_pairs=max(options.loop_pairs, LOOP_PAIRS))
        result, staged, second = video_pass(source, work / "pass1", denser, dense, max_frames, stages, masks)
        passes.append(second)
        if second["registered"] >= needed(options.min_registered, second["frames"]):
            return result, staged, passes, work / "pass1"
    raise InputError(failure(passes, options.min_registered, limit), source,
                     "walk more slowly around the subject and keep it in view, add light (blur and noise leave too "
                     "few features), or " + ("record at a higher frame rate" if limit.startswith("every") else
                     "sample more frames with --fps (up to --max-frames)") + "; lower --min-registered to accept a "
                     "partial model")


def failure(passes: list[dict], min_registered: float, limit: str) -> str:
    """What the video passes tried and got, in one line (``limit``: why there was no denser pass)."""
    first = passes[0]
    text = (f"only {first['registered']} of {first['frames']} video frames registered at {first['fps']:g} fps "
            f"(need {needed(min_registered, first['frames'])})")
    if len(passes) > 1:
        p = passes[1]
        text += (f"; sampled again at {p['fps']:g} fps and matched in sequence with loop detection: "
                 f"{p['registered']} of {p['frames']} (need {needed(min_registered, p['frames'])})")
    else:
        text += f"; {limit}"
    return text
