"""``video``: clips in 10-bit H.264 and HEVC, VP9, 16-bit FFV1, MPEG-4 and with a rotation must decode upright;
corrupt, empty, truncated, audio-only, one- and two-frame, 2x2-pixel, FIFO, device and looping "videos" refused.
``capture``: photos too small for SfM, a clip sampled above its own frame rate or at almost none."""

from __future__ import annotations

import os
from pathlib import Path


def _ffmpeg(*args: str) -> None:
    import subprocess

    import imageio_ffmpeg

    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-loglevel", "error", "-y", *args], check=True)


def _videos(d: Path) -> dict[str, Path]:
    """Clips of 12 noise frames (64x48, 4 fps) in several codecs and shapes, and hostile files named as videos."""
    d.mkdir(parents=True)
    src = d / "src_%02d.png"
    import numpy as np
    from PIL import Image

    for i in range(12):
        Image.fromarray((np.random.default_rng(i).random((48, 64, 3)) * 255).astype(np.uint8)).save(str(src) % i)
    v = {}
    enc = {"h264.mp4": ["-c:v", "libx264", "-pix_fmt", "yuv420p"], "h264_10bit.mp4": ["-c:v", "libx264", "-pix_fmt",
           "yuv420p10le"], "hevc_10bit.mp4": ["-c:v", "libx265", "-pix_fmt", "yuv420p10le", "-x265-params", "log-level=0"],
           "vp9.webm": ["-c:v", "libvpx-vp9", "-pix_fmt", "yuv420p"], "ffv1_rgb48.mkv": ["-c:v", "ffv1", "-pix_fmt",
           "rgb48le"], "mpeg4.avi": ["-c:v", "mpeg4"]}
    for name, codec in enc.items():
        v[name] = d / name
        _ffmpeg("-framerate", "4", "-i", str(src), *codec, str(v[name]))
    v["rotated.mp4"] = d / "rotated.mp4"  # a phone held upright: 64x48 stored, shown 48x64
    _ffmpeg("-display_rotation", "90", "-i", str(v["h264.mp4"]), "-c", "copy", str(v["rotated.mp4"]))
    v["one_frame.mp4"] = d / "one_frame.mp4"
    _ffmpeg("-framerate", "4", "-i", str(src) % 0, "-c:v", "libx264", "-pix_fmt", "yuv420p", str(v["one_frame.mp4"]))
    v["two_frames.mp4"] = d / "two_frames.mp4"
    _ffmpeg("-framerate", "4", "-i", str(src), "-frames:v", "2", "-c:v", "libx264", "-pix_fmt", "yuv420p",
            str(v["two_frames.mp4"]))
    v["audio_only.mp4"] = d / "audio_only.mp4"
    _ffmpeg("-f", "lavfi", "-i", "anullsrc=r=8000:cl=mono", "-t", "1", "-c:a", "aac", str(v["audio_only.mp4"]))
    v["tiny_2x2.mkv"] = d / "tiny_2x2.mkv"
    _ffmpeg("-framerate", "4", "-i", str(src), "-vf", "scale=2:2", "-c:v", "ffv1", str(v["tiny_2x2.mkv"]))
    for f in d.glob("src_*.png"):
        f.unlink()
    good = v["h264.mp4"].read_bytes()
    for name, data in {"zero_length.mp4": b"", "noise.mp4": os.urandom(50_000), "truncated.mp4": good[: len(good) // 2],
                       "header_only.mp4": good[:64], "text.mov": b"not a video\n" * 100}.items():
        v[name] = d / name
        v[name].write_bytes(data)
    v["png_as.mp4"] = d / "png_as.mp4"  # a photo renamed: ffmpeg reads it as a one-frame clip
    Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(v["png_as.mp4"], format="PNG")
    v["fifo.mp4"] = d / "fifo.mp4"
    os.mkfifo(v["fifo.mp4"])
    v["dev_zero.mp4"] = d / "dev_zero.mp4"
    os.symlink("/dev/zero", v["dev_zero.mp4"])
    v["folder.mp4"] = d / "folder.mp4"
    v["folder.mp4"].mkdir()
    v["loop.mp4"] = d / "loop.mp4"
    os.symlink("loop.mp4", v["loop.mp4"])
    return v


def video_cases(work: Path) -> list[dict]:
    """``video``: clips a phone or an editor writes (10-bit, HEVC, VP9, rotated, 16-bit FFV1, odd codecs) must decode
    upright; corrupt, empty, truncated, audio-only, one-frame and non-file "videos" are refused naming the file."""
    v = _videos(work / "videos")
    out = []
    for name, (w, h) in {"h264.mp4": (64, 48), "h264_10bit.mp4": (64, 48), "hevc_10bit.mp4": (64, 48),
                         "vp9.webm": (64, 48), "ffv1_rgb48.mkv": (64, 48), "mpeg4.avi": (64, 48), "rotated.mp4": (48, 64)}.items():
        out.append({"class": "video", "args": ["probe_video", str(v[name]), str(w), str(h)], "named": None, "accept": True})
    tiny = ["--threads", "1", "--quiet"]
    for name in ("zero_length.mp4", "noise.mp4", "truncated.mp4", "header_only.mp4", "audio_only.mp4", "one_frame.mp4",
                 "two_frames.mp4", "png_as.mp4", "tiny_2x2.mkv", "fifo.mp4", "dev_zero.mp4", "loop.mp4", "text.mov"):
        out.append({"class": "video", "args": ["process", str(v[name]), "--out", "{out}", *tiny], "named": str(v[name])})
        if name in ("zero_length.mp4", "noise.mp4", "truncated.mp4", "audio_only.mp4", "one_frame.mp4", "fifo.mp4"):
            out.append({"class": "video", "args": ["reconstruct", str(v[name]), "--out", "{out}", "--threads", "1",
                                                   "--no-viewer"], "named": str(v[name])})
    out.append({"class": "video", "args": ["process", str(v["one_frame.mp4"]), "--fps", "30", "--out", "{out}", *tiny],
                "named": str(v["one_frame.mp4"])})
    out.append({"class": "video", "args": ["process", str(v["h264.mp4"]), "--max-frames", "1", "--out", "{out}", *tiny],
                "named": "--max-frames"})
    return out



def capture_cases(work: Path) -> list[dict]:
    """``capture``: photos too small for SfM (pycolmap crashed on them) and a 4 fps clip sampled at 240 fps
    (capped at the clip's rate) or at 1e-30 fps (blamed on --fps)."""
    import imageio_ffmpeg
    import numpy as np
    from PIL import Image

    out = []
    for w, h in ((1, 1), (4, 4), (8, 8), (1, 64), (64, 2)):
        d = work / "capture" / f"tiny_{w}x{h}"
        d.mkdir(parents=True)
        for i in range(4):
            Image.fromarray((np.random.default_rng(i).random((h, w, 3)) * 255).astype(np.uint8)).save(d / f"p{i}.png")
        out.append({"class": "capture", "args": ["process", str(d), "--out", "{out}", "--threads", "1"],
                    "named": str(d / "p0.png")})
    clip = work / "capture" / "clip4fps.mp4"
    writer = imageio_ffmpeg.write_frames(str(clip), (64, 64), fps=4, quality=8, macro_block_size=16)
    writer.send(None)
    for i in range(12):
        writer.send((np.random.default_rng(i).random((64, 64, 3)) * 255).astype(np.uint8).tobytes())
    writer.close()
    out.append({"class": "capture", "args": ["process", str(clip), "--fps", "240", "--out", "{out}", "--threads", "1",
                                             "--quiet"], "named": str(clip)})
    for fps in ("1e-30", "0.01"):
        out.append({"class": "capture", "args": ["process", str(clip), "--fps", fps, "--out", "{out}"],
                    "named": "--fps"})
    return out

