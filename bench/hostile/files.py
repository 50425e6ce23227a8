"""``files``: pose files with bad focal fields, deep JSON, NumPy headers claiming more than the file holds, unreadable
mesh files as ``--mesh`` and as a scene's ground truth, broken checkpoint metadata."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

TJ = "transforms_train.json"
TINY = ["--threads", "1"]


def file_cases(p: dict[str, Path], work: Path) -> list[dict]:
    """Every ``files`` case, each refused naming the broken file."""
    meta = json.loads((p["scene"] / TJ).read_text())
    return (_pose_field_cases(p, work, meta) + _json_cases(p, work, meta) + _npy_cases(p, work)
            + _mesh_cases(p, work, meta) + _checkpoint_cases(p, work))


def _pose_field_cases(p: dict[str, Path], work: Path, meta: dict) -> list[dict]:
    """The blender scene's pose file with a bad focal, frame list or image size field."""
    C, O = str(p["ck"]), "{out}"
    edits = {"angle_neg": {"camera_angle_x": -0.5}, "angle_pi": {"camera_angle_x": 3.1416},
             "angle_big": {"camera_angle_x": 1e308}, "angle_str": {"camera_angle_x": "wide"},
             "angle_null_fl0": {"camera_angle_x": None, "fl_x": 0}, "fl_neg": {"fl_x": -10.0},
             "fl_nan": {"fl_x": float("nan")}, "angle_list": {"camera_angle_x": [0.5]},
             "frames_dict": {"frames": {"a": 1}}, "frames_str": {"frames": "many"},
             "w_zero": {"w": 0, "h": 0, "fl_x": 10.0}, "w_huge": {"w": 10**9, "h": 10**9, "fl_x": 10.0}}
    out = []
    for name, edit in edits.items():
        d = work / "files" / name
        shutil.copytree(p["scene"], d)
        (d / TJ).write_text(json.dumps({**meta, **edit}))
        for verb in (["inspect", str(d), "--out", O], ["render", "--scene", str(d), "--ckpt", C, "--out", O,
                                                        "--no-video", *TINY]):
            out.append({"class": "files", "args": verb, "named": str(d / TJ)})
    return out


def _json_cases(p: dict[str, Path], work: Path, meta: dict) -> list[dict]:
    """The pose file as deep JSON, a 5000-digit number, NUL bytes, a cut BOM-led text."""
    out = []
    for name, text in {"deep_list": "[" * 50_000 + "]" * 50_000, "deep_dict": '{"a":' * 50_000 + "1" + "}" * 50_000,
                       "huge_number": '{"camera_angle_x": 1' + "0" * 5000 + ', "frames": []}',
                       "nul_bytes": "\0" * 100, "bom": "\ufeff" + json.dumps(meta)[:20]}.items():
        d = work / "files" / name
        shutil.copytree(p["scene"], d)
        (d / TJ).write_text(text)
        out.append({"class": "files", "args": ["inspect", str(d), "--out", "{out}"], "named": str(d / TJ)})
    return out


def _npy_cases(p: dict[str, Path], work: Path) -> list[dict]:
    """The llff scene's poses_bounds.npy with a header claiming more rows, columns or axes than the file holds."""
    out = []
    raw = (p["llff"] / "poses_bounds.npy").read_bytes()
    for name, shape in {"rows_1e13": "(10000000000000, 17)", "rows_1e6": "(1000000, 17)", "cols_huge": "(3, 10000000000)",
                        "ndim5": "(3, 17, 1000, 1000, 1000)", "negative": "(-3, 17)"}.items():
        d = work / "files" / f"npy_{name}"
        shutil.copytree(p["llff"], d)
        head = re.sub(rb"'shape': \(\d+, 17\)", f"'shape': {shape}".encode(), raw[:128])
        (d / "poses_bounds.npy").write_bytes(head[:127].ljust(127) + b"\n" + raw[128:])
        out.append({"class": "files", "args": ["inspect", str(d), "--out", "{out}"],
                    "named": str(d / "poses_bounds.npy")})
    return out


PLY_HEAD = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
MESHES = {"empty.ply": "", "text.ply": "just words\n", "ascii_bad_row.ply":
          PLY_HEAD + "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\nx\n3 0 1 2\n",
          "ascii_no_faces.ply": PLY_HEAD + "end_header\n0 0 0\n1 0 0\n0 1 0\n",
          "ascii_nan.ply": PLY_HEAD + "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                           "nan 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
          "obj_garbage.obj": "v a b c\nf 1 2 x\n", "glb_garbage.glb": "glTF\x02\x00\x00\x00garbage",
          "binary_trunc.ply": "ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\n"
                              "property float y\nproperty float z\nend_header\n\x00\x01"}
"""Unreadable mesh files: ``{file name: its text}``."""


def _mesh_cases(p: dict[str, Path], work: Path, meta: dict) -> list[dict]:
    """Each of MESHES as ``export`` / ``finetune --mesh``, and (the .ply ones) as a scene's ground-truth mesh."""
    S, C, O = str(p["scene"]), str(p["ck"]), "{out}"
    out = []
    for fname, text in MESHES.items():
        f = work / "files" / "meshes" / fname
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(text)
        for verb in (["export", "--scene", S, "--ckpt", C, "--mesh", str(f), "--out", O, *TINY],
                     ["finetune", "--scene", S, "--ckpt", C, "--mesh", str(f), "--out", O, "--seconds", "1", *TINY]):
            out.append({"class": "files", "args": verb, "named": str(f)})
        if fname.endswith(".ply"):
            d = work / "files" / f"gt_{fname[:-4]}"
            shutil.copytree(p["scene"], d)
            (d / "mesh.ply").write_text(text)
            (d / TJ).write_text(json.dumps({**meta, "mesh_path": "mesh.ply"}))
            out.append({"class": "files", "args": ["mesh", "--scene", str(d), "--model", "floor", "--out", O + ".ply",
                                                   *TINY], "named": str(d / "mesh.ply")})
    return out


def _checkpoint_cases(p: dict[str, Path], work: Path) -> list[dict]:
    """The checkpoint's meta.json as deep JSON, NUL bytes, a bare number, a null model config."""
    out = []
    for name, text in {"deep": "[" * 50_000 + "]" * 50_000, "nul": "\0\0\0", "number": "42", "model_null":
                       json.dumps({"preset": "omnirecon-tiny", "model_config": None})}.items():
        d = work / "files" / f"ck_{name}"
        shutil.copytree(p["ck"], d)
        (d / "meta.json").write_text(text)
        out.append({"class": "files", "args": ["render", "--scene", str(p["scene"]), "--ckpt", str(d), "--out", "{out}",
                                               "--no-video", *TINY], "named": str(d / "meta.json")})
    return out
