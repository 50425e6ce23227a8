"""``resume``: `reconstruct --resume / --no-resume` over an ``OUT.partial`` that is the user's folder, a file, a link
(or holds a link as its record folder), or a garbage record: refused or started over, no file of the user's lost."""

from __future__ import annotations

import os
from pathlib import Path


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

