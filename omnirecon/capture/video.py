"""Frames sampled from a video with imageio-ffmpeg (ffmpeg's ``fps`` filter), saved as PNG; its duration."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from omnirecon.errors import InputError


def sample_frames(video: Path, dest: Path, fps: float, max_frames: int = 300, on_frame=None) -> list[str]:
    """Decode ``video`` at ``fps`` frames per second into ``dest/frame_00000.png``, ...; returns the names.

    ffmpeg applies the stream's rotation metadata, so frames come out upright. At most ``max_frames``
    are kept (the first ones). ``on_frame(i, expected)`` is called after each saved frame
    (``expected``: the count estimated from the duration, or None). A file ffmpeg cannot decode, or
    one that gives no frame, raises :class:`InputError`.
    """
    import imageio_ffmpeg  # lazy: the optional 'video' extra

    video, dest = Path(video), Path(dest)
    if not video.is_file():
        raise InputError("video file does not exist", video, "check the path")
    if not (fps > 0):
        raise InputError(f"--fps must be positive, got {fps}", None, "use e.g. --fps 2")
    dest.mkdir(parents=True, exist_ok=True)
    names: list[str] = []
    try:
        gen = imageio_ffmpeg.read_frames(str(video), output_params=["-vf", f"fps={fps}"])
        meta = next(gen)
        ffmpeg = gen.gi_frame.f_locals.get("process")  # read_frames' Popen, for _close_pipes
        try:
            w, h = meta["size"]
            duration = float(meta.get("duration") or 0)
            expected = min(max_frames, max(1, round(duration * fps))) if duration > 0 else None
            for frame in gen:
                a = np.frombuffer(frame, np.uint8).reshape(h, w, 3)
                name = f"frame_{len(names):05d}.png"
                Image.fromarray(a).save(dest / name)
                names.append(name)
                if on_frame is not None:
                    on_frame(len(names), expected)
                if len(names) >= max_frames:
                    break
        finally:
            gen.close()
            _close_pipes(ffmpeg)
    except (OSError, RuntimeError, ValueError, KeyError, StopIteration) as e:
        detail = str(e).strip().splitlines()[-1][:160] if str(e).strip() else type(e).__name__
        raise InputError(f"cannot decode the video ({detail})", video,
                         "check that the file is a complete video (mp4/mov/webm), or extract its frames "
                         "into a folder of images and pass that") from e
    if not names:
        raise InputError("the video gave no frames", video, "check the file, or lower --fps for a very short clip")
    return names


def clip_rate(video: Path) -> tuple[float | None, float | None]:
    """``(frames per second, seconds)`` of ``video`` from its header (None where ffmpeg gives none or cannot
    read it: :func:`sample_frames` then names the file)."""
    import imageio_ffmpeg  # lazy: the optional 'video' extra

    try:
        gen = imageio_ffmpeg.read_frames(str(video))
        try:
            meta = next(gen)
        finally:
            gen.close()
    except (OSError, RuntimeError, ValueError, KeyError, StopIteration):
        return None, None
    fps, duration = (float(meta.get(k) or 0) for k in ("fps", "duration"))
    return (fps if fps > 0 else None), (duration if duration > 0 else None)


def _close_pipes(process) -> None:
    """Close the pipes of imageio-ffmpeg's ffmpeg process: ``read_frames`` (0.8.1) closes them only when ffmpeg still
    runs, so a video read to its end left stdin and stdout to the garbage collector, which printed a ResourceWarning
    on every video run."""
    for pipe in (getattr(process, "stdin", None), getattr(process, "stdout", None)):
        if pipe is not None and not pipe.closed:
            pipe.close()


def video_duration(video: Path) -> float | None:
    """Length of ``video`` in seconds from its container (None when ffmpeg does not tell)."""
    return clip_rate(video)[1]
