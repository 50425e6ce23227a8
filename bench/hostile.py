"""A hostile-input set of its own (not the rows of tests/commands/test_malformed.py), run the way a new user
would hit it, for BENCHMARKS' "Hostile inputs" section (issue 28, inputs part).

    python -m bench hostile                  # every case, ~5 min at 1 thread
    python -m bench hostile --limit 40       # a quick look

Classes of cases (each built here, in a temporary folder):

* ``numbers``: every numeric option of every command (``omnirecon.options.numeric_fields``) with values a
  user mistypes: ``nan``, ``inf``, ``-inf``, below and above its range, and a huge size.
* ``photos``: scenes of three formats and photo folders for ``process`` whose images are decompression
  bombs, truncated, empty, FIFOs, devices, folders or links to them; plus unusual *valid* photos (16-bit,
  palette, CMYK, grey + alpha), which must be *accepted* (exit 0, no traceback).
* ``files``: pose files with bad focal fields, deep JSON, NumPy headers claiming more than the file
  holds, unreadable mesh files as ``--mesh`` and as a scene's ground truth, broken checkpoint metadata.
* ``outputs``: ``--out`` under /proc, under a file, through a dangling link, on a device.
* ``outputs_user``: ``--out`` over a file (or into a folder) the user wrote: a mesh set's files, a bench
  JSON, a train folder's config, a file added to an earlier render output; refused, nothing replaced or lost.
* ``capture``: photos too small for SfM, a clip sampled above its own frame rate or at almost none.
* ``memory``: ``mesh --voxel`` and ``finetune --val-every`` values whose allocation exceeds the memory.
* ``viewer``: HTTP requests with several ``Host`` headers (must be 400), clients that disconnect, and up to
  1,000 connections that stall in their headers while a normal request must be answered within 1 s; bad requests
  (huge or endless headers, garbage, HTTP/0.9, traversal in every spelling, CONNECT, a body never sent), a
  slowloris trickle, clients that request a large file and never read it, connections that send nothing.

The set written for the verbs and options added since (:func:`fresh_cases`):

* ``video``: clips in 10-bit H.264 and HEVC, VP9, 16-bit FFV1, MPEG-4 and with a rotation must decode upright;
  corrupt, empty, truncated, audio-only, one- and two-frame, 2x2-pixel, FIFO, device and looping "videos" refused.
* ``folders_valid`` / ``folders``: photo folders of mixed sizes, CMYK / grey JPEG, 16-bit PNG, EXIF-rotated,
  WebP, BMP, TIFF (staged); and with a truncated JPEG / PNG, a JPEG claiming 65000 px sides, a link loop, a file
  reading fails on, HEIC, an animated GIF, a folder linking to itself, none / one / two photos (refused).
* ``options``: depth sources, surfaces (``--surface auto|fusion|coherent|poisson``), view lists, finetune blends
  and fills on a broken mesh, ``--guided.*`` on render / eval, ``process --learned`` and ``--masks`` (all black),
  ``bench --realtime --face-budget`` with a bad mesh; refused naming the option or file, or accepted.
* ``resume``: `reconstruct --resume / --no-resume` over an ``OUT.partial`` that is the user's folder, a file, a link
  (or holds a link as its record folder), or a garbage record: refused or started over, no file of the user's lost.

A refused case counts as handled only with exit 2, one stderr line ``omnirecon: error: ...`` naming the
file or option and carrying a ``(fix: ...)`` clause, no traceback, nothing added, removed or changed
under the fixtures, no ``--out`` and nothing in the working folder. Each case runs in a forked child (the
package imported once in the parent) with a time limit (a hang) and an address-space limit (killed for
memory). Writes ``bench/results/hostile.json`` with a provenance header.

Size: the case builders of fifteen classes, the forked runner and the verdict are one measurement; the builders
are short functions read one at a time.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import signal
import stat
import struct
import sys
import tempfile
import time
import zlib
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

TIMEOUT = 60.0
"""Seconds before a case counts as a hang."""
EXTRA_MEMORY = 6 * 2**30
"""Address space a case may add to the parent's before it counts as killed for memory."""


# ---------------------------------------------------------------------------- fixtures
def _png_bomb(path: Path, w: int, h: int) -> None:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\0" * 4096)) + chunk(b"IEND", b""))


def build(root: Path) -> dict[str, Path]:
    """Every fixture the cases name, under ``root``."""

    from omnirecon.engine.checkpoint import save_checkpoint
    from omnirecon.models.registry import build_model
    from tests.data.test_bad_input import blender_scene, colmap_scene, llff_scene, tiny_image

    p: dict[str, Path] = {"root": root}
    p["scene"] = blender_scene(root / "scene")
    (p["scene"] / "transforms_test.json").write_text((p["scene"] / "transforms_train.json").read_text())
    p["llff"] = llff_scene(root / "llff")
    p["colmap"] = colmap_scene(root / "colmap")
    save_checkpoint(root / "ck", build_model("omnirecon-tiny", {"coarse_samples": 4, "fine_samples": 2,
                                                                 "volume_resolution": 8}), "omnirecon-tiny")
    p["ck"] = root / "ck"
    p["photos"] = root / "photos"
    for i in range(4):
        tiny_image(p["photos"] / f"p{i}.png", w=32, h=24, seed=i)
    p["a_file"] = root / "a_file.txt"
    p["a_file"].write_text("x")
    p["dangling"] = root / "dangling"
    os.symlink(root / "no" / "such", p["dangling"])
    return p


def _bad_image(path: Path, kind: str) -> None:
    """Replace the image at ``path`` by a hostile one of ``kind``."""
    if path.exists() or path.is_symlink():
        path.unlink()
    if kind.startswith("bomb"):
        side = {"bomb_wide": (2**31 - 1, 1), "bomb_tall": (1, 2**31 - 1), "bomb": (100_000, 100_000),
                "bomb_mid": (20_000, 20_000)}[kind]
        _png_bomb(path, *side)
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated_header":
        path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\x0dIHDR")
    elif kind == "jpeg_header":
        path.write_bytes(b"\xff\xd8\xff\xe0\x00\x10JFIF\x00")
    elif kind == "zero_size":
        _png_bomb(path, 0, 0)
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "dev_zero":
        os.symlink("/dev/zero", path)
    elif kind == "dev_null":
        os.symlink("/dev/null", path)
    elif kind == "folder":
        path.mkdir()
    elif kind == "self_link":
        os.symlink(path.name, path)
    elif kind == "text":
        path.write_text("this is text, not a picture\n" * 20)
    else:
        raise ValueError(kind)


BAD_IMAGES = ["bomb", "bomb_wide", "bomb_tall", "bomb_mid", "empty", "truncated_header", "jpeg_header",
              "zero_size", "fifo", "dev_zero", "dev_null", "folder", "self_link", "text"]
GOOD_MODES = ["I;16", "P", "PA", "CMYK", "LA", "RGBA", "1", "L"]


def _good_image(path: Path, mode: str, seed: int) -> Path:
    import numpy as np
    from PIL import Image

    rng = np.random.default_rng(seed)
    if mode in ("I;16", "I"):
        im = Image.fromarray((rng.random((8, 8)) * 65535).astype(np.uint16))
        im = im if mode == "I;16" else im.convert("I")
    else:
        im = Image.fromarray((rng.random((8, 8, 3)) * 255).astype(np.uint8)).convert(mode)
    target = path.with_suffix(".tif") if mode in ("CMYK", "PA") else path
    im.save(target)
    return target


# ---------------------------------------------------------------------------- cases
def cases(p: dict[str, Path], work: Path) -> list[dict]:
    """Every case: ``{"class", "args", "named" (text the message must hold) or None, "accept" (exit 0 wanted)}``."""
    import shutil

    from omnirecon.cli import COMMANDS, _load
    from omnirecon.options import numeric_fields, rule_for

    S, C, O = str(p["scene"]), str(p["ck"]), "{out}"
    tiny = ["--threads", "1"]
    base = {
        "demo": ["demo", "--out", O], "synth": ["synth", "--out", O], "process": ["process", str(p["photos"]), "--out", O],
        "inspect": ["inspect", S, "--out", O], "eval": ["eval", "--ckpt", C, "--scenes", S, "--out", O],
        "render": ["render", "--scene", S, "--ckpt", C, "--out", O, "--no-video"],
        "train": ["train", "--data", S, "--out", O, "--model", "gpnr-tiny", "--steps", "2"],
        "mesh": ["mesh", "--scene", S, "--model", "floor", "--out", O + ".ply"],
        "lift": ["lift", "--ckpt", C, "--scene", S, "--out", O], "edit": ["edit", "--ckpt", C, "--scene", S, "--out", O],
        "pet": ["pet", "--ckpt", C, "--scene", S, "--out", O], "finetune": ["finetune", "--ckpt", C, "--scene", S, "--out", O],
        "export": ["export", "--ckpt", C, "--scene", S, "--out", O], "view": ["view", S, "--no-browser"],
        "bench": ["bench", "--ckpt", C, "--out", O + ".json"], "reconstruct": ["reconstruct", S, "--out", O],
    }
    out: list[dict] = []
    # -- numbers: every numeric option of every command
    for name, spec in COMMANDS.items():
        if name == "doctor":
            continue
        cls = _load(spec)
        import typing
        hints = typing.get_type_hints(cls)
        for field in numeric_fields(cls):
            rule = rule_for(name, field)
            flag = "--" + field.replace("_", "-")
            text = str(hints[field])
            is_float = "float" in text
            arity = 2 if "tuple[int, int]" in text else 1
            values = ["nan", "inf", "-inf"] if is_float else ["1.5", "1e400"]
            if rule.lo is not None:
                lo = rule.lo - (1 if not is_float else max(1.0, abs(rule.lo)))
                values.append(str(int(lo)) if not is_float else repr(float(lo)))
            if rule.hi is not None:
                values.append(str(int(rule.hi * 10 + 1)) if not is_float else repr(float(rule.hi * 10 + 1)))
            for v in values:
                threads = tiny if "threads" in hints and field != "threads" else []
                out.append({"class": "numbers", "args": [*base[name], *threads, flag, *([v] * arity)],
                            "named": flag})
    # -- photos: three scene formats and a photo folder, one image hostile
    targets = {"blender": (p["scene"], "train/r_1.png"), "llff": (p["llff"], "images/img_001.png"),
               "colmap": (p["colmap"], "images/im1.png"), "photos": (p["photos"], "p1.png")}
    for fmt, (scene, rel) in targets.items():
        for kind in BAD_IMAGES:
            d = work / "photos_cases" / f"{fmt}_{kind}"
            shutil.copytree(scene, d, symlinks=True)
            _bad_image(d / rel, kind)
            cmd = ["process", str(d), "--out", O] if fmt == "photos" else ["inspect", str(d), "--out", O]
            out.append({"class": "photos", "args": cmd, "named": str(d / rel)})
            if fmt == "blender" and kind in ("bomb", "fifo", "dev_zero", "truncated_header"):
                for verb in (["render", "--scene", str(d), "--ckpt", C, "--out", O, "--no-video", *tiny],
                             ["mesh", "--scene", str(d), "--model", "floor", "--out", O + ".ply", *tiny],
                             ["train", "--data", str(d), "--out", O, "--model", "gpnr-tiny", "--steps", "1", *tiny]):
                    out.append({"class": "photos", "args": verb, "named": str(d / rel)})
        if fmt in ("blender", "photos"):
            for i, mode in enumerate(GOOD_MODES):
                d = work / "photos_cases" / f"{fmt}_good_{mode.replace(';', '')}"
                shutil.copytree(scene, d, symlinks=True)
                if fmt == "photos":  # every photo in this mode (distinct content): must be staged, not refused
                    for j in range(4):
                        (d / f"p{j}.png").unlink()
                        _good_image(d / f"p{j}.png", mode, seed=10 * i + j)
                    out.append({"class": "photos_valid", "args": ["inspect_photos", str(d)], "named": None,
                                "accept": True})
                else:
                    (d / rel).unlink()
                    made = _good_image(d / rel, mode, seed=i)
                    if made != d / rel:
                        continue  # the blender reader looks for .png
                    out.append({"class": "photos_valid", "args": ["inspect", str(d), "--out", O], "named": None,
                                "accept": True})
    # -- files: pose fields, JSON, NumPy headers, meshes, checkpoint metadata
    tj = "transforms_train.json"
    meta = json.loads((p["scene"] / tj).read_text())
    edits = {"angle_neg": {"camera_angle_x": -0.5}, "angle_pi": {"camera_angle_x": 3.1416},
             "angle_big": {"camera_angle_x": 1e308}, "angle_str": {"camera_angle_x": "wide"},
             "angle_null_fl0": {"camera_angle_x": None, "fl_x": 0}, "fl_neg": {"fl_x": -10.0},
             "fl_nan": {"fl_x": float("nan")}, "angle_list": {"camera_angle_x": [0.5]},
             "frames_dict": {"frames": {"a": 1}}, "frames_str": {"frames": "many"},
             "w_zero": {"w": 0, "h": 0, "fl_x": 10.0}, "w_huge": {"w": 10**9, "h": 10**9, "fl_x": 10.0}}
    for name, edit in edits.items():
        d = work / "files" / name
        shutil.copytree(p["scene"], d)
        (d / tj).write_text(json.dumps({**meta, **edit}))
        for verb in (["inspect", str(d), "--out", O], ["render", "--scene", str(d), "--ckpt", C, "--out", O,
                                                        "--no-video", *tiny]):
            out.append({"class": "files", "args": verb, "named": str(d / tj)})
    for name, text in {"deep_list": "[" * 50_000 + "]" * 50_000, "deep_dict": '{"a":' * 50_000 + "1" + "}" * 50_000,
                       "huge_number": '{"camera_angle_x": 1' + "0" * 5000 + ', "frames": []}',
                       "nul_bytes": "\0" * 100, "bom": "\ufeff" + json.dumps(meta)[:20]}.items():
        d = work / "files" / name
        shutil.copytree(p["scene"], d)
        (d / tj).write_text(text)
        out.append({"class": "files", "args": ["inspect", str(d), "--out", O], "named": str(d / tj)})
    raw = (p["llff"] / "poses_bounds.npy").read_bytes()
    for name, shape in {"rows_1e13": "(10000000000000, 17)", "rows_1e6": "(1000000, 17)", "cols_huge": "(3, 10000000000)",
                        "ndim5": "(3, 17, 1000, 1000, 1000)", "negative": "(-3, 17)"}.items():
        d = work / "files" / f"npy_{name}"
        shutil.copytree(p["llff"], d)
        head = re.sub(rb"'shape': \(\d+, 17\)", f"'shape': {shape}".encode(), raw[:128])
        (d / "poses_bounds.npy").write_bytes(head[:127].ljust(127) + b"\n" + raw[128:])
        out.append({"class": "files", "args": ["inspect", str(d), "--out", O], "named": str(d / "poses_bounds.npy")})
    ply_head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
    meshes = {"empty.ply": "", "text.ply": "just words\n", "ascii_bad_row.ply":
              ply_head + "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\nx\n3 0 1 2\n",
              "ascii_no_faces.ply": ply_head + "end_header\n0 0 0\n1 0 0\n0 1 0\n",
              "ascii_nan.ply": ply_head + "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                               "nan 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
              "obj_garbage.obj": "v a b c\nf 1 2 x\n", "glb_garbage.glb": "glTF\x02\x00\x00\x00garbage",
              "binary_trunc.ply": "ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\n"
                                  "property float y\nproperty float z\nend_header\n\x00\x01"}
    for fname, text in meshes.items():
        f = work / "files" / "meshes" / fname
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(text)
        for verb in (["export", "--scene", S, "--ckpt", C, "--mesh", str(f), "--out", O, *tiny],
                     ["finetune", "--scene", S, "--ckpt", C, "--mesh", str(f), "--out", O, "--seconds", "1", *tiny]):
            out.append({"class": "files", "args": verb, "named": str(f)})
        if fname.endswith(".ply"):
            d = work / "files" / f"gt_{fname[:-4]}"
            shutil.copytree(p["scene"], d)
            (d / "mesh.ply").write_text(text)
            (d / tj).write_text(json.dumps({**meta, "mesh_path": "mesh.ply"}))
            out.append({"class": "files", "args": ["mesh", "--scene", str(d), "--model", "floor", "--out", O + ".ply",
                                                   *tiny], "named": str(d / "mesh.ply")})
    for name, text in {"deep": "[" * 50_000 + "]" * 50_000, "nul": "\0\0\0", "number": "42", "model_null":
                       json.dumps({"preset": "omnirecon-tiny", "model_config": None})}.items():
        d = work / "files" / f"ck_{name}"
        shutil.copytree(p["ck"], d)
        (d / "meta.json").write_text(text)
        out.append({"class": "files", "args": ["render", "--scene", S, "--ckpt", str(d), "--out", O, "--no-video", *tiny],
                    "named": str(d / "meta.json")})
    # -- outputs
    for name, target in {"proc": "/proc/omnirecon-hostile/x", "sys": "/sys/omnirecon-hostile", "under_file":
                         str(p["a_file"]) + "/sub", "dangling": str(p["dangling"]), "dev_null": "/dev/null"}.items():
        named = target if name != "under_file" else str(p["a_file"])
        for verb in (["process", str(p["photos"]), "--out", target],
                     ["render", "--scene", S, "--ckpt", C, "--out", target, "--no-video", *tiny],
                     ["synth", "--out", target], ["inspect", S, "--out", target]):
            out.append({"class": "outputs", "args": verb, "named": named})
    # -- viewer
    for hosts in [("127.0.0.1", "evil.example"), ("evil.example", "127.0.0.1"), ("127.0.0.1", "127.0.0.1"),
                  ("localhost", "127.0.0.1"), ("127.0.0.1", ""), ("127.0.0.1", "evil.example", "127.0.0.1")]:
        out.append({"class": "viewer", "args": ["http_hosts", *hosts], "named": None})
    for n in (1, 2, 5):
        out.append({"class": "viewer", "args": ["http_disconnect", str(n)], "named": None})
    for n in (100, 1000):
        out.append({"class": "viewer", "args": ["http_stalled", str(n)], "named": None})
    out += user_file_cases(p, work) + capture_cases(work) + memory_cases(p)
    return out + fresh_cases(p, work)


def fresh_cases(p: dict[str, Path], work: Path) -> list[dict]:
    """The set written for the verbs and options added since the classes above (issue 46 item 4)."""
    viewer = [{"class": "viewer", "args": ["http_raw", name], "named": None} for name in BAD_REQUESTS]
    viewer += [{"class": "viewer", "args": [kind, str(n)], "named": None}
               for kind, n in (("http_trickle", 50), ("http_slow_readers", 100), ("http_silent", 1000))]
    return (video_cases(work) + valid_folder_cases(work) + folder_cases(work) + option_cases(p, work)
            + resume_cases(p, work) + viewer)


def memory_cases(p: dict[str, Path]) -> list[dict]:
    """``memory``: options that size an allocation past the memory (checked against it, not a count)."""
    S, C, tiny = str(p["scene"]), str(p["ck"]), ["--threads", "1"]
    out = [{"class": "memory", "named": "--voxel", "args": ["mesh", "--scene", S, "--model", "floor", "--out",
                                                             "{out}.ply", "--voxel", v, *tiny]}
           for v in ("0.0005", "0.0001", "1e-7")]
    out += [{"class": "memory", "named": "--val-every", "args": ["finetune", "--scene", S, "--ckpt", C, "--out", "{out}",
                                                                 "--val-every", v, *tiny]} for v in ("1e-9", "1e-6")]
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


def user_file_cases(p: dict[str, Path], work: Path) -> list[dict]:
    """``outputs_user``: single-file outputs and output folders over files the user wrote (never replaced,
    never deleted, never filled without --overwrite)."""
    S, C, tiny = str(p["scene"]), str(p["ck"]), ["--threads", "1"]
    out = []
    for name in ("m.ply", "m.obj", "m_preview.png", "m_metrics.json"):
        d = work / "user_files" / name.replace(".", "_")
        d.mkdir(parents=True)
        (d / name).write_text("the user's file\n")
        for first in [name] if name.startswith("m.") else ["m.ply", "m.obj"]:
            out.append({"class": "outputs_user", "named": str(d / name), "args": [
                "mesh", "--scene", S, "--model", "floor", "--out", str(d / first), *tiny]})
    d = work / "user_files" / "bench"
    d.mkdir()
    (d / "b.json").write_text('{"mine": 1}')
    out.append({"class": "outputs_user", "named": str(d / "b.json"),
                "args": ["bench", "--ckpt", C, "--quick", "--out", str(d / "b.json")]})
    d = work / "user_files" / "train"
    d.mkdir()
    (d / "config.json").write_text('{"mine": 1}')
    (d / "metrics.jsonl").write_text('{"mine": 1}\n')
    out.append({"class": "outputs_user", "named": str(d), "args": [
        "train", "--data", S, "--out", str(d), "--model", "gpnr-tiny", "--steps", "1", *tiny]})
    d = work / "user_files" / "render"  # an earlier render output, and a file the user added in it
    (d / "frames").mkdir(parents=True)
    (d / "frames" / "0000.png").write_bytes(b"\x89PNG")
    (d / ".omnirecon-output.json").write_text(json.dumps({"tool": "omnirecon", "command": "render",
                                                           "written": "earlier", "files": ["frames/0000.png"]}))
    for added in ("frames/notes.txt", "notes.txt"):
        (d / added).write_text("the user's notes\n")
    out.append({"class": "outputs_user", "named": str(d / "frames" / "notes.txt"), "args": [
        "render", "--scene", S, "--ckpt", C, "--out", str(d), "--no-video", *tiny]})
    return out


# ---------------------------------------------------------------------------- fresh set (issue 46 item 4)
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


def _photo(path: Path, seed: int, size=(40, 30), mode="RGB", **save) -> Path:
    import numpy as np
    from PIL import Image

    im = Image.fromarray((np.random.default_rng(seed).random((size[1], size[0], 3)) * 255).astype(np.uint8))
    path.parent.mkdir(parents=True, exist_ok=True)
    im.convert(mode).save(path, **save)
    return path


def _photo16(path: Path, seed: int, channels: int) -> Path:
    import cv2
    import numpy as np

    a = (np.random.default_rng(seed).random((30, 40, channels)) * 65535).astype(np.uint16)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), a if channels > 1 else a[..., 0])
    return path


def _exif_rotated(path: Path, seed: int) -> Path:
    from PIL import Image

    _photo(path, seed, format="JPEG")
    im = Image.open(path)
    exif = im.getexif()
    exif[0x0112] = 6  # rotate 90 degrees on display
    im.save(path, format="JPEG", exif=exif)
    return path


def valid_folder_cases(work: Path) -> list[dict]:
    """``folders_valid``: photo folders a user's devices write (mixed sizes, CMYK JPEG, 16-bit colour and grey PNG,
    grey JPEG, EXIF-rotated JPEG, upper-case extensions, WebP, BMP, TIFF): staged as `process` stages them."""
    makers = {
        "mixed_sizes": lambda d, i: _photo(d / f"p{i}.jpg", i, size=(40 + 8 * i, 30 + 4 * i)),
        "cmyk_jpeg": lambda d, i: _photo(d / f"p{i}.jpg", i, mode="CMYK", format="JPEG"),
        "rgb16_png": lambda d, i: _photo16(d / f"p{i}.png", i, 3),
        "grey16_png": lambda d, i: _photo16(d / f"p{i}.png", i, 1),
        "grey_jpeg": lambda d, i: _photo(d / f"p{i}.jpg", i, mode="L", format="JPEG"),
        "exif_rotated": lambda d, i: _exif_rotated(d / f"p{i}.jpg", i),
        "upper_ext": lambda d, i: _photo(d / f"P{i}.JPG", i, format="JPEG"),
        "webp": lambda d, i: _photo(d / f"p{i}.webp", i, format="WEBP"),
        "bmp": lambda d, i: _photo(d / f"p{i}.bmp", i, format="BMP"),
        "jpeg_named_png": lambda d, i: _photo(d / f"p{i}.png", i, format="JPEG"),
        "mixed_formats": lambda d, i: _photo(d / f"p{i}.{('jpg', 'png', 'webp', 'tif')[i]}", i,
                                             format=("JPEG", "PNG", "WEBP", "TIFF")[i]),
    }
    out = []
    for name, make in makers.items():
        d = work / "folders" / f"valid_{name}"
        for i in range(4):
            make(d, i)
        out.append({"class": "folders_valid", "args": ["inspect_photos", str(d), *["per_image"] * (name == "mixed_sizes")],
                    "named": None, "accept": True})
    d = work / "folders" / "valid_mixed_sizes"  # one camera model for all: refused, naming the photo and the option
    out.append({"class": "folders_valid", "args": ["process", str(d), "--out", "{out}", "--threads", "1"],
                "named": "--per-image-cameras"})
    return out


def _hostile_member(d: Path, kind: str) -> Path:
    """Put a hostile member into the photo folder ``d``; the path the error must name."""
    good = (d / "p0.jpg").read_bytes()
    bad = d / "p9.jpg"
    if kind == "truncated_jpeg":
        bad.write_bytes(good[: len(good) // 2])
    elif kind == "truncated_png":
        _photo(d / "p9.png", 9, format="PNG")
        bad = d / "p9.png"
        bad.write_bytes(bad.read_bytes()[:-40])
    elif kind == "jpeg_bomb":  # a SOF0 frame header claiming 65000 x 65000
        i = good.index(b"\xff\xc0")
        bad.write_bytes(good[: i + 5] + struct.pack(">HH", 65000, 65000) + good[i + 9:])
    elif kind == "link_loop":
        os.symlink("p8.jpg", bad)
        os.symlink("p9.jpg", d / "p8.jpg")
    elif kind == "unreadable":  # reading it fails (EIO), as an unreadable file does for a user without the right
        os.symlink("/proc/self/mem", bad)
    elif kind == "heic":
        bad = d / "p9.heic"
        bad.write_bytes(b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic" + os.urandom(200))
    elif kind == "gif_animated":
        from PIL import Image

        bad = d / "p9.gif"
        frames = [Image.open(d / f"p{i}.jpg").convert("P") for i in range(2)]
        frames[0].save(bad, save_all=True, append_images=frames[1:])
        return bad
    elif kind == "zero_width_jpeg":
        i = good.index(b"\xff\xc0")
        bad.write_bytes(good[: i + 5] + struct.pack(">HH", 30, 0) + good[i + 9:])
    elif kind == "text_jpg":
        bad.write_text("a note, not a photo\n")
    else:
        raise ValueError(kind)
    return bad


def folder_cases(work: Path) -> list[dict]:
    """``folders``: photo folders with one hostile member (truncated JPEG / PNG, a JPEG claiming 65000 px sides, a link
    loop, a file reading fails on, HEIC, an animated GIF, a zero-width JPEG, text named .jpg), a folder linking to
    itself, an empty one, one photo: `process` and `reconstruct` refuse naming the member, leave nothing."""
    out = []
    tiny = ["--threads", "1", "--quiet"]
    for kind in ("truncated_jpeg", "truncated_png", "jpeg_bomb", "link_loop", "unreadable", "heic", "gif_animated",
                 "zero_width_jpeg", "text_jpg"):
        d = work / "folders" / kind
        for i in range(4):
            _photo(d / f"p{i}.jpg", i, format="JPEG")
        bad = _hostile_member(d, kind)
        named = str(d) if kind == "link_loop" else str(bad)  # either link of the loop
        out.append({"class": "folders", "args": ["process", str(d), "--out", "{out}", *tiny], "named": named})
        out.append({"class": "folders", "args": ["reconstruct", str(d), "--out", "{out}", "--threads", "1",
                                                 "--no-viewer"], "named": named})
    d = work / "folders" / "dir_loop"
    for i in range(4):
        _photo(d / f"p{i}.jpg", i, format="JPEG")
    os.symlink("..", d / "sub")
    out.append({"class": "folders", "args": ["process", str(d), "--out", "{out}", *tiny], "named": str(d)})
    for name, count in (("empty", 0), ("one_photo", 1), ("two_photos", 2)):
        d = work / "folders" / name
        d.mkdir(parents=True)
        for i in range(count):
            _photo(d / f"p{i}.jpg", i, format="JPEG")
        for verb in ("process", "reconstruct"):
            out.append({"class": "folders", "args": [verb, str(d), "--out", "{out}", "--threads", "1"], "named": str(d)})
    return out


def option_cases(p: dict[str, Path], work: Path) -> list[dict]:
    """``options``: the verbs' newer options given what they cannot use: surfaces and depth sources a scene cannot
    give, view lists out of range, unknown mesh suffixes, finetune blends and fills without what they need,
    ``--guided.*`` on a model without depth, ``process --learned`` and ``--masks`` misuse, ``bench --realtime`` with a
    bad mesh; each refused naming the option or file (or accepted when it is a valid choice)."""
    S, C, tiny = str(p["scene"]), str(p["ck"]), ["--threads", "1"]
    mesh = ["mesh", "--scene", S, "--model", "floor", "--out", "{out}.ply", *tiny]
    out = [{"class": "options", "args": [*mesh, *extra], "named": named} for extra, named in [
        (["--depth", "oracle"], "--depth"), (["--views", "99"], "--views"), (["--views", "-1"], "--views"),
        (["--views", "x"], "--views"), (["--views", "0", "0", "0"], "--views"), (["--out", "{out}.xyz"], "{out}.xyz"),
        (["--shifts", "nan"], "--shifts"), (["--shifts", "1e9"], "--shifts")]]
    for extra in (["--depth", "model"], ["--num-views", "50", "--views", "all"], ["--out", "{out}.ply", "{out}.ply"],
                  ["--surface", "poisson"], ["--surface", "poisson", "--fusion", "reference"],
                  ["--fusion", "reference", "--complete"], ["--surface", "coherent"], ["--surface", "fusion"],
                  ["--surface", "auto"], ["--surface", "coherent", "--depth", "stereo", "--no-complete"]):
        out.append({"class": "options", "args": [*mesh, *extra], "named": S, "accept_or_refuse": True})
    mf = work / "options" / "not_a_mesh.ply"
    mf.parent.mkdir(parents=True, exist_ok=True)
    mf.write_text("ply\nformat ascii 1.0\nend_header\n")
    ft = ["finetune", "--ckpt", C, "--scene", S, "--out", "{out}", "--seconds", "1", *tiny]
    out += [{"class": "options", "args": [*ft, *extra], "named": named} for extra, named in [
        (["--views", "99"], "--views"), (["--views", "-3"], "--views"), (["--mesh", str(work / "no_such.ply")],
        str(work / "no_such.ply")), (["--mesh", str(work)], str(work)), (["--mesh", str(mf)], str(mf)),
        (["--blend", "angle", "--angle-sources", "--mesh", str(mf)], str(mf)),
        (["--fill", "nearest", "--mesh", str(mf)], str(mf))]]
    rnd = ["render", "--scene", S, "--out", "{out}", "--no-video", "--num-views", "3", "--frames", "2", *tiny]
    out += [{"class": "options", "args": [*rnd, *extra], "named": named, "accept_or_refuse": True} for extra, named in [
        (["--model", "floor", "--guided.on"], "--guided.on"), (["--ckpt", C, "--keyframes", "99"], "--keyframes"),
        (["--ckpt", C, "--path", "interp", "--keyframes", "0", "0"], "--keyframes"), (["--ckpt", C, "--guided.on"], S)]]
    out.append({"class": "options", "args": [*ft, "--val-views", "100"], "named": "--val-views", "accept_or_refuse": True})
    out.append({"class": "options", "named": S, "args": ["eval", "--model", "floor", "--scenes", S, "--out",
                                                                      "{out}", "--guided.on", *tiny]})
    out.append({"class": "options", "named": str(work / "nope"), "args": ["eval", "--ckpt", C, "--scenes", str(work / "nope"),
                                                                          "--out", "{out}", "--guided.on", *tiny]})
    ph = str(p["photos"])
    out += [{"class": "options", "args": ["process", ph, "--out", "{out}", "--threads", "1", *extra], "named": named}
            for extra, named in [(["--learned", "prefer"], ph), (["--masks", str(work / "no_masks")], str(work / "no_masks")),
                                 (["--masks", str(p["a_file"])], str(p["a_file"])),
                                 (["--masks", str(_zero_masks(work, p["photos"]))], str(work / "masks_zero")),
                                 (["--matcher", "sequential", "--overlap", "0"], "--overlap")]]
    bn = ["bench", "--ckpt", C, "--quick", "--out", "{out}.json", "--realtime"]
    out += [{"class": "options", "args": [*bn, *extra], "named": named} for extra, named in [
        (["--mesh", str(work / "no_such.ply")], str(work / "no_such.ply")), (["--mesh", str(mf)], str(mf)),
        (["--scene", str(work / "nope")], str(work / "nope")), (["--face-budget", "-5"], "--face-budget")]]
    return out


def _zero_masks(work: Path, photos: Path) -> Path:
    import numpy as np
    from PIL import Image

    d = work / "masks_zero"
    d.mkdir(parents=True, exist_ok=True)
    for f in sorted(photos.glob("*.png")):
        w, h = Image.open(f).size
        Image.fromarray(np.zeros((h, w), np.uint8)).save(d / f.name)
    return d


def _partial_setup(kind: str):
    """What ``OUT.partial`` (and a folder of the user's beside it) holds before the run: the paths to keep intact."""
    def setup(out: Path) -> list[Path]:
        part, user = out.parent / f"{out.name}.partial", out.parent / f"{out.name}_mine"
        user.mkdir()
        (user / "notes.txt").write_text("the user's\n")
        if kind == "user_folder":
            part.mkdir()
            (part / "notes.txt").write_text("the user's\n")
            return [part, user]
        if kind == "a_file":
            part.write_text("the user's\n")
            return [part, user]
        if kind == "link_to_user":
            os.symlink(user, part)
            return [part, user]
        if kind == "link_inside":  # the tool's own work folder, its record folder a link to the user's folder
            part.mkdir()
            os.symlink(user, part / ".omnirecon-partial")
            return [part, user]
        (part / ".omnirecon-partial").mkdir(parents=True)
        (part / ".omnirecon-partial" / "stages.json").write_text(
            {"garbage": "{{{", "deep": "[" * 50_000 + "]" * 50_000, "list": '{"stages": [1, 2]}'}[kind])
        (part / "scene").mkdir()
        return [user]
    return setup


def resume_cases(p: dict[str, Path], work: Path) -> list[dict]:
    """``resume``: `reconstruct`'s work folder ``OUT.partial`` as a user or a crash leaves it: the user's own folder of
    that name, a file of that name, a link to the user's folder (or a record folder linking there), a kept record that
    is garbage (the run starts over and finishes), with ``--resume`` and ``--no-resume``. No file of the user's lost."""
    from omnirecon.data.synth.generate import SynthOptions, generate_scene

    scene = generate_scene(work / "resume_scene", 0, SynthOptions(rig="object", views=8, resolution=32))
    rec = ["reconstruct", str(scene), "--out", "{out}", "--threads", "1", "--no-viewer", "--resolution", "32",
           "--mesh-resolution", "32", "--finetune-seconds", "0", "--frames", "2"]
    out = []
    for kind in ("user_folder", "a_file", "link_to_user", "link_inside", "garbage", "deep", "list"):
        for flag in ("--resume", "--no-resume"):
            refused = kind in ("user_folder", "a_file", "link_to_user")
            out.append({"class": "resume", "args": [*rec, flag], "setup": _partial_setup(kind),
                        "named": "{out}.partial" if refused or kind == "link_inside" else None,
                        "accept": not refused and kind != "link_inside", "accept_or_refuse": kind == "link_inside"})
    return out


# ---------------------------------------------------------------------------- running
def _tree(root: Path) -> dict[str, tuple]:
    out = {}
    for dirpath, dirs, files in os.walk(root):
        for n in dirs + files:
            q = Path(dirpath) / n
            st = os.lstat(q)
            # a folder's own time changes with a lock file made and removed in it: its entries are compared
            out[str(q.relative_to(root))] = (st.st_mode, st.st_size, 0 if stat.S_ISDIR(st.st_mode) else st.st_mtime_ns)
    return out


def _state(path: Path):
    """What a user's file, link or folder (its entries) is, for a before/after comparison (None: gone)."""
    if not path.exists() and not path.is_symlink():
        return None
    if path.is_dir() and not path.is_symlink():
        return _tree(path)
    st = os.lstat(path)
    return st.st_mode, st.st_size, st.st_mtime_ns, os.readlink(path) if path.is_symlink() else None


def _child(argv: list[str], cwd: Path, err: Path, limit: int) -> None:
    os.chdir(cwd)
    fd = os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    os.dup2(fd, 2)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    sys.stderr = os.fdopen(2, "w", buffering=1)
    sys.stdout = os.fdopen(1, "w")
    rc = 1
    try:
        if argv[0] == "inspect_photos":  # valid unusual photos: stage them as process does (COLMAP not run)
            from omnirecon.capture.images import stage_images
            stage_images(Path(argv[1]), cwd / "staged", shared_camera=argv[2:] != ["per_image"])
            import shutil
            shutil.rmtree(cwd / "staged")
            rc = 0
        elif argv[0] == "probe_video":  # a valid clip: sampled as process samples it, upright, at its shown size
            from PIL import Image

            from omnirecon.capture.video import sample_frames

            names = sample_frames(Path(argv[1]), cwd / "staged", fps=4)
            size = Image.open(cwd / "staged" / names[0]).size
            import shutil
            shutil.rmtree(cwd / "staged")
            rc = 0 if size == (int(argv[2]), int(argv[3])) and len(names) >= 10 else 3
            print(f"{len(names)} frames of {size[0]}x{size[1]}", file=sys.stderr)
        elif argv[0].startswith("http_"):
            rc = _http_case(argv)
        else:
            from omnirecon.cli import main
            rc = main(argv)
    except BaseException:  # noqa: BLE001 - what escapes main is what a user would see
        import traceback
        traceback.print_exc()
        rc = 1
    sys.stderr.flush()
    os._exit(rc if isinstance(rc, int) else 1)


def http_exchange(port: int, request: bytes) -> tuple[int, bytes]:
    """Send ``request`` to 127.0.0.1:``port`` exactly as given; the status code and body of the answer."""
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(request)
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), body


def stalled_then_get(port: int, stalled: int, timeout: float = 1.0) -> tuple[int, float]:
    """Open ``stalled`` connections to 127.0.0.1:``port`` that send a request line and never finish their
    headers, then send one normal ``GET /index.html``: its status (0 when no answer came within ``timeout``
    seconds) and the seconds it took. The stalled sockets are closed before returning."""
    import socket

    if stalled + 64 > resource.getrlimit(resource.RLIMIT_NOFILE)[0]:
        hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, stalled + 256), hard))
    held = []
    try:
        for _ in range(stalled):
            s = socket.create_connection(("127.0.0.1", port), timeout=10)
            s.sendall(b"GET /index.html HTTP/1.1\r\n")
            held.append(s)
        t0 = time.perf_counter()
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
                s.sendall(b"GET /index.html HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
                head = s.recv(64)
            status = int(head.split()[1]) if head.startswith(b"HTTP/") else 0
        except OSError:
            status = 0
        return status, time.perf_counter() - t0
    finally:
        for s in held:
            s.close()


H = "Host: 127.0.0.1\r\n"
BAD_REQUESTS = {
    "big_header": f"GET /index.html HTTP/1.0\r\n{H}X-Big: {'a' * 70_000}\r\n\r\n",
    "many_headers": "GET /index.html HTTP/1.0\r\n" + H + "".join(f"X-{i}: v\r\n" for i in range(300)) + "\r\n",
    "long_line": f"GET /{'a' * 70_000} HTTP/1.0\r\n{H}\r\n", "garbage": "\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03\r\n\r\n",
    "http09": "GET /index.html\r\n\r\n", "post_huge": f"POST /index.html HTTP/1.0\r\n{H}Content-Length: 10000000000\r\n\r\n",
    "bad_version": f"GET /index.html HTTP/9.9\r\n{H}\r\n", "no_colon": "GET /index.html HTTP/1.0\r\nHost 127.0.0.1\r\n\r\n",
    "nul_path": f"GET /index.html%00.png HTTP/1.0\r\n{H}\r\n", "dotdot": f"GET /../../../../etc/passwd HTTP/1.0\r\n{H}\r\n",
    "dotdot_encoded": f"GET /%2e%2e/%2e%2e/%2e%2e/etc/passwd HTTP/1.0\r\n{H}\r\n",
    "slash_encoded": f"GET /..%2f..%2f..%2fetc%2fpasswd HTTP/1.0\r\n{H}\r\n", "double_slash": f"GET //etc/passwd HTTP/1.0\r\n{H}\r\n",
    "absolute": f"GET http://127.0.0.1/../etc/passwd HTTP/1.0\r\n{H}\r\n", "bad_utf8": f"GET /%ff%fe HTTP/1.0\r\n{H}\r\n",
    "connect": f"CONNECT 127.0.0.1:22 HTTP/1.1\r\n{H}\r\n", "trace": f"TRACE / HTTP/1.1\r\n{H}\r\n",
    "long_host": f"GET /index.html HTTP/1.0\r\nHost: {'a' * 60_000}\r\n\r\n", "bare_lf": "GET /index.html HTTP/1.0\nHost: 127.0.0.1\n\n",
    "pipelined": f"GET /index.html HTTP/1.1\r\n{H}\r\nGET /big.bin HTTP/1.1\r\n{H}\r\n",
    "range_bad": f"GET /big.bin HTTP/1.1\r\n{H}Range: bytes=999999999-1\r\nConnection: close\r\n\r\n",
}
"""Requests a hostile client sends the viewer: each gets an answer that serves nothing outside the folder (or the
connection is closed), and the server then answers a normal GET within 1 s."""


def _raw_answer(port: int, raw: bytes) -> bytes:
    """What the server sends back to ``raw`` (the client half-closes after sending; b"" when it closes first)."""
    import socket

    data = b""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        try:
            s.sendall(raw)
            s.shutdown(socket.SHUT_WR)
            while chunk := s.recv(65536):
                data += chunk
        except OSError:  # reset by the server (a request it refused while still sending)
            pass
    return data


def _clients(port: int, kind: str, n: int) -> list:
    """``n`` hostile connections: ``http_trickle`` sends a request a byte at a time (slowloris), ``http_slow_readers``
    requests the 16 MB file and never reads, ``http_silent`` connects and sends nothing."""
    import socket

    held = []
    for _ in range(n):
        s = socket.create_connection(("127.0.0.1", port), timeout=10)
        if kind == "http_slow_readers":
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            s.sendall(f"GET /big.bin HTTP/1.0\r\n{H}\r\n".encode())
        elif kind == "http_trickle":
            s.sendall(b"G")
        held.append(s)
    if kind == "http_trickle":
        for byte in b"ET /index.html HTTP/1.0\r\nX-":
            time.sleep(0.05)
            for s in held:
                s.sendall(bytes([byte]))
    time.sleep(0.3)
    return held


def _http_case(argv: list[str]) -> int:
    """0 when the viewer answers as it must: 400 for several Host headers; quiet and alive after disconnects."""
    import socket

    from omnirecon.viewer.server import ViewerServer

    folder = Path(tempfile.mkdtemp(prefix="hostile_view_"))
    (folder / "index.html").write_text("<p>ok</p>")
    (folder / "big.bin").write_bytes(os.urandom(16 * 2**20))
    server = ViewerServer(folder, port=0, quiet=True)
    server.start()
    port = server.server_address[1]

    def get(raw: bytes) -> int:
        return http_exchange(port, raw)[0]
    try:
        if argv[0] == "http_stalled":  # the stalled connections must not keep a normal request waiting
            status, seconds = stalled_then_get(port, int(argv[1]), timeout=1.0)
            print(f"GET answered {status} in {seconds:.3f} s beside {argv[1]} stalled connections", file=sys.stderr)
            return 0 if status == 200 and seconds <= 1.0 else 3
        if argv[0] == "http_raw":  # a bad request: no file outside the folder, and the server goes on
            answer = _raw_answer(port, BAD_REQUESTS[argv[1]].encode("latin-1"))
            status = answer.split(b" ", 2)[1].decode() if answer.startswith(b"HTTP/") else "closed"
            print(f"answered {status}", file=sys.stderr)
            leaked = b"root:" in answer or (status == "200" and argv[1] not in ("bare_lf", "pipelined", "range_bad"))
            return 3 if leaked or get(b"GET /index.html HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n") != 200 else 0
        if argv[0] in ("http_trickle", "http_slow_readers", "http_silent"):
            held = _clients(port, argv[0], int(argv[1]))
            try:
                status, seconds = stalled_then_get(port, 0, timeout=1.0)
            finally:
                for s in held:
                    s.close()
            print(f"GET answered {status} in {seconds:.3f} s beside {argv[1]} {argv[0][5:]} connections", file=sys.stderr)
            return 0 if status == 200 and seconds <= 1.0 else 3
        if argv[0] == "http_hosts":
            head = "GET /index.html HTTP/1.1\r\n" + "".join(f"Host: {h}\r\n" for h in argv[1:]) + "Connection: close\r\n\r\n"
            return 0 if get(head.encode()) == 400 else 3
        for _ in range(int(argv[1])):
            s = socket.create_connection(("127.0.0.1", port), timeout=10)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            s.sendall(b"GET /big.bin HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
            s.recv(1024)
            s.close()
        time.sleep(0.5)
        return 0 if get(b"GET /index.html HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n") == 200 else 3
    finally:
        server.stop()
        import shutil

        shutil.rmtree(folder, ignore_errors=True)


def run_case(case: dict, p: dict[str, Path], work: Path, limit: int) -> dict:
    cwd = Path(tempfile.mkdtemp(prefix="cwd_", dir=work))
    out = cwd.parent / (cwd.name + "_out")
    argv = [a.replace("{out}", str(out)) for a in case["args"]]
    named = case["named"].replace("{out}", str(out)) if case["named"] else None
    users = case["setup"](out) if case.get("setup") else []  # what the user (or a crash) left at OUT before the run
    users_before = [_state(u) for u in users]
    err = work / "stderr.txt"
    before = _tree(p["root"])
    t0 = time.perf_counter()
    pid = os.fork()
    if pid == 0:
        _child(argv, cwd, err, limit)
    status, verdict = None, None
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.perf_counter() - t0 > TIMEOUT:
            os.kill(pid, signal.SIGKILL)  # our own child
            os.waitpid(pid, 0)
            verdict = "hang"
            break
        time.sleep(0.02)
    seconds = time.perf_counter() - t0
    text = err.read_text(errors="replace") if err.exists() else ""
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    rc = os.waitstatus_to_exitcode(status) if verdict is None else None
    changed = _tree(p["root"]) != before or [_state(u) for u in users] != users_before
    kept = "rerun the same command to continue" in text  # reconstruct keeps its finished stages in OUT.partial, and says so
    leftovers = [str(q) for q in cwd.parent.glob(out.name + "*") if not (kept and q.name == f"{out.name}.partial")
                 and q not in users] + \
        [str(q) for q in cwd.rglob("*")]
    if verdict is None:
        if rc is not None and rc < 0:
            verdict = "killed"
        elif "MemoryError" in text:
            verdict = "memory"
        elif changed:
            verdict = "data_changed"
        elif case.get("accept") or case["class"] == "viewer" or (case.get("accept_or_refuse") and rc == 0):
            verdict = "handled" if rc == 0 and "Traceback" not in text else "not_handled"
        elif (rc == 2 and len(lines) == 1 and lines[0].startswith("omnirecon: error: ") and "(fix: " in lines[0]
              and "Traceback" not in text and not leftovers and named in lines[0]):
            verdict = "handled"
        else:
            verdict = "not_handled"
    return {"class": case["class"], "args": [a.replace(str(p["root"]), "<fx>").replace(str(work), "<work>")
                                             for a in argv],
            "verdict": verdict, "exit": rc, "seconds": round(seconds, 2), "lines": len(lines),
            "message": (lines[-1] if lines else "")[:300].replace(str(work), "<work>"), "leftovers": len(leftovers)}


def _vm_bytes() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    return 0


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE / "results" / "hostile.json")
    parser.add_argument("--limit", type=int, default=None, help="run only the first N cases (a quick look)")
    parser.add_argument("--only", default=None, help="only cases of these classes (comma-separated)")
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    from omnirecon.cli import COMMANDS, _load
    from omnirecon.provenance import provenance

    for spec in COMMANDS.values():  # imported once: every forked case starts warm
        _load(spec)
    import omnirecon.capture.images  # noqa: F401
    import omnirecon.viewer.server  # noqa: F401

    work = Path(tempfile.mkdtemp(prefix="hostile_"))
    p = build(work / "fx")
    todo = cases(p, work / "fx" / "cases")
    if args.only:
        todo = [c for c in todo if c["class"] in args.only.split(",")]
    todo = todo[: args.limit] if args.limit else todo
    limit = _vm_bytes() + EXTRA_MEMORY
    t0 = time.perf_counter()
    results = []
    for i, case in enumerate(todo):
        r = run_case(case, p, work, limit)
        results.append(r)
        if r["verdict"] != "handled":
            print(f"[{i + 1}/{len(todo)}] {r['verdict']}: {' '.join(r['args'])[:160]}\n    {r['message'][:200]}",
                  flush=True)
    per: dict[str, dict] = {}
    for r in results:
        c = per.setdefault(r["class"], {"cases": 0, "handled": 0})
        c["cases"] += 1
        c["handled"] += r["verdict"] == "handled"
    verdicts = {v: sum(r["verdict"] == v for r in results) for v in
                ("handled", "not_handled", "data_changed", "hang", "memory", "killed")}
    record = {"provenance": provenance(seed=0, load_average=os.getloadavg()), "cases": len(results),
              "handled": verdicts["handled"], "handled_fraction": verdicts["handled"] / max(1, len(results)),
              "verdicts": verdicts, "per_class": per, "seconds": round(time.perf_counter() - t0, 1),
              "timeout_s": TIMEOUT, "extra_memory_gb": EXTRA_MEMORY / 2**30,
              "failures": [r for r in results if r["verdict"] != "handled"],
              "results": [{"class": r["class"], "verdict": r["verdict"], "exit": r["exit"], "seconds": r["seconds"],
                           "args": " ".join(r["args"])[:200], "message": r["message"][:160]} for r in results]}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1, default=str))
    print(f"{record['handled']}/{record['cases']} handled ({100 * record['handled_fraction']:.1f} %); "
          f"{verdicts}; {record['seconds']} s -> {args.out}")
    import shutil
    shutil.rmtree(work, ignore_errors=True)
    return record

