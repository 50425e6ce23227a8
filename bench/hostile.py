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
  1,000 connections that stall in their headers while a normal request must be answered within 1 s.

A refused case counts as handled only with exit 2, one stderr line ``omnirecon: error: ...`` naming the
file or option and carrying a ``(fix: ...)`` clause, no traceback, nothing added, removed or changed
under the fixtures, no ``--out`` and nothing in the working folder. Each case runs in a forked child (the
package imported once in the parent) with a time limit (a hang) and an address-space limit (killed for
memory). Writes ``bench/results/hostile.json`` with a provenance header.

Size: the case builders of five classes, the forked runner and the verdict are one measurement; the builders
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
    return out + user_file_cases(p, work) + capture_cases(work) + memory_cases(p)


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
            stage_images(Path(argv[1]), cwd / "staged")
            import shutil
            shutil.rmtree(cwd / "staged")
            rc = 0
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
    changed = _tree(p["root"]) != before
    kept = "rerun the same command to continue" in text  # reconstruct keeps its finished stages in OUT.partial, and says so
    leftovers = [str(q) for q in cwd.parent.glob(out.name + "*") if not (kept and q.name == f"{out.name}.partial")] + \
        [str(q) for q in cwd.rglob("*")]
    if verdict is None:
        if rc is not None and rc < 0:
            verdict = "killed"
        elif "MemoryError" in text:
            verdict = "memory"
        elif changed:
            verdict = "data_changed"
        elif case.get("accept") or case["class"] == "viewer":
            verdict = "handled" if rc == 0 and "Traceback" not in text else "not_handled"
        elif (rc == 2 and len(lines) == 1 and lines[0].startswith("omnirecon: error: ") and "(fix: " in lines[0]
              and "Traceback" not in text and not leftovers and case["named"] in lines[0]):
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
    parser.add_argument("--only", default=None, help="only cases of this class")
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
        todo = [c for c in todo if c["class"] == args.only]
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

