"""``outputs``: ``--out`` under /proc, under a file, through a dangling link, on a device; ``outputs_user``: ``--out``
over a file (or into a folder) the user wrote: a mesh set's files, a bench JSON, a train folder's config, a file
added to an earlier render output; refused, nothing replaced or lost."""

from __future__ import annotations

import json
from pathlib import Path


def output_cases(p: dict[str, Path]) -> list[dict]:
    """``--out`` of four verbs where nothing can be written; refused naming the place (or the file in the way)."""
    S, C, tiny = str(p["scene"]), str(p["ck"]), ["--threads", "1"]
    out = []
    for name, target in {"proc": "/proc/omnirecon-hostile/x", "sys": "/sys/omnirecon-hostile", "under_file":
                         str(p["a_file"]) + "/sub", "dangling": str(p["dangling"]), "dev_null": "/dev/null"}.items():
        named = target if name != "under_file" else str(p["a_file"])
        for verb in (["process", str(p["photos"]), "--out", target],
                     ["render", "--scene", S, "--ckpt", C, "--out", target, "--no-video", *tiny],
                     ["synth", "--out", target], ["inspect", S, "--out", target]):
            out.append({"class": "outputs", "args": verb, "named": named})
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

