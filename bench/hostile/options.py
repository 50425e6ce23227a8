"""``options``: depth sources, surfaces (``--surface auto|fusion|coherent|poisson``), view lists, finetune blends and
fills on a broken mesh, ``--guided.*`` on render / eval, ``process --learned`` and ``--masks`` (all black), ``bench
--realtime --face-budget`` with a bad mesh; refused naming the option or file, or accepted. ``memory``: ``mesh
--voxel`` and ``finetune --val-every`` values whose allocation exceeds the memory."""

from __future__ import annotations

from pathlib import Path


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



def memory_cases(p: dict[str, Path]) -> list[dict]:
    """``memory``: options that size an allocation past the memory (checked against it, not a count)."""
    S, C, tiny = str(p["scene"]), str(p["ck"]), ["--threads", "1"]
    out = [{"class": "memory", "named": "--voxel", "args": ["mesh", "--scene", S, "--model", "floor", "--out",
                                                             "{out}.ply", "--voxel", v, *tiny]}
           for v in ("0.0005", "0.0001", "1e-7")]
    out += [{"class": "memory", "named": "--val-every", "args": ["finetune", "--scene", S, "--ckpt", C, "--out", "{out}",
                                                                 "--val-every", v, *tiny]} for v in ("1e-9", "1e-6")]
    return out

