"""The mesh path's PSNR against seconds of CPU tuning, with coverage, on real and procedural scenes.

    python -m bench finetune_curves --scene fern=../shared/data/llff/fern --mesh fern=MESH.ply --seconds 300
    python -m bench finetune_curves --scene demo=PATH --mesh demo=MESH.ply --seconds 300
    python -m bench finetune_curves --scene fern=... --mesh fern=MESH.ply --collect   # an interrupted run's curve
    python -m bench finetune_curves --scene fox=../shared/data/instant_ngp/fox --split extrapolation

Without ``--mesh`` for a scene, its mesh is ``reconstruct``'s mesh stage (``omnirecon mesh --views <the training
views>``, omnirecon-tiny, 3 sources per depth map, the photos' size or ``--resolution``) made from the split's
training views alone, into ``outputs/bench/finetune_curves/<name>/mesh.ply`` (reused when there).
With ``--split extrapolation`` the held-out views are the extrapolation split's test views (``omnirecon finetune
--split extrapolation``: beyond the training views' arc, or a walk's last stretch); its rows are named
``<name> (extrapolation)``.

Per scene: ``omnirecon finetune`` with its defaults (each pixel's ``--nearest 6`` sources, the encoder + appearance
branch at 5e-4, pixels per step, precision, ``--val-choice``; the row records them) and the
given mesh (the project's own ``omnirecon mesh --views all`` meshes; the JSON records the depth source
from the mesh's ``*_metrics.json``), images at the photos' own resolution, the clock this process's CPU
time (``--clock cpu --threads 1``: other jobs on the machine do not shrink the budget), scored on the
protocol's held-out views at 0, 10, 30, 60 (and 300) s: the whole image and, on scenes with masks, the
objects. The returned state is the best on validation views (never sources, never held-out views; its
gain is on what the scene is scored by, the other score guarded: ``omnirecon finetune --val-guard``), so the
held-out curve is what a user gets
when tuning stops at that time; the validation scores are recorded apart. Each run merges its scene
into ``bench/results/finetune_curves.json`` under a file lock (scenes can run in separate processes) and
copies the curve and the before/after picture to ``bench/results/figures/``.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import shutil
from pathlib import Path

import torch

from omnirecon.data.io import write_json

ROOT = Path(__file__).resolve().parents[1]
TIMES = (0.0, 10.0, 30.0, 60.0)


def mesh_record(mesh: Path) -> dict:
    """How the mesh was made, from ``<mesh>_metrics.json`` when ``omnirecon mesh`` wrote one."""
    file = mesh.with_name(mesh.stem + "_metrics.json")
    if not file.is_file():
        return {}
    m = json.loads(file.read_text())
    return {"depth": m.get("options", {}).get("depth"), "resolution": m.get("resolution"), "views": m.get("views"),
            "faces": m.get("faces", {}).get("completed"), "model": m.get("model", {}).get("name"),
            "images_to_mesh_s": m.get("seconds", {}).get("images_to_mesh")}


SPLIT_SUFFIX = {"protocol": "", "extrapolation": " (extrapolation)"}
"""A results row's name: the scene's, with this suffix per ``--split``."""


def slug(key: str) -> str:
    """A file-name form of a results row's name (``fox (extrapolation)`` -> ``fox_extrapolation``)."""
    return key.replace(" (", "_").replace(")", "").replace(" ", "_")


def work_dir(name: str) -> Path:
    return ROOT / "outputs" / "bench" / "finetune_curves" / slug(name)


def split_mesh(key: str, path: Path, split: str, resolution: int | None, threads: int) -> Path:
    """``reconstruct``'s mesh stage of ``path`` made from the training views of ``split`` alone (module docstring)
    into the row's work folder, unless already there."""
    from dataclasses import replace

    from omnirecon.data import detect_format
    from omnirecon.engine.protocols import protocol_for, targets_and_pool
    from omnirecon.engine.scenes import load_at_resolution, photo_side
    from omnirecon.workflows.mesh import MeshConfig, run_mesh

    out = work_dir(key) / "mesh.ply"
    if out.is_file():
        return out
    fmt = detect_format(path)
    proto = protocol_for(path, fmt)
    proto = replace(proto, split=split) if split == "extrapolation" else proto
    side = resolution or photo_side(path, fmt=fmt)
    scene = load_at_resolution(path, side, proto.background, fmt)
    targets, pool = targets_and_pool(proto, scene)
    train = [i for i in pool if i not in set(targets) | set(scene.splits.get("test", []))]  # finetune's training views
    out.parent.mkdir(parents=True, exist_ok=True)
    run_mesh(MeshConfig(scene=path, ckpt=ROOT / "checkpoints" / "omnirecon-tiny", views=tuple(map(str, train)),
                        num_views=3, out=(out,), resolution=side, threads=threads))
    return out


def run_scene(name: str, path: Path, mesh: Path, seconds: float, threads: int, resolution: int | None,
              save: bool = False, split: str = "protocol") -> None:
    from omnirecon.workflows.finetune import FinetuneConfig, run_finetune

    times = tuple(t for t in (*TIMES, 300.0) if t <= seconds)
    run_finetune(FinetuneConfig(ckpt=ROOT / "checkpoints" / "omnirecon-tiny", scene=path, mesh=mesh, seconds=seconds,
                                eval_at=times, clock="cpu", threads=threads, out=work_dir(name), resolution=resolution,
                                max_held_out=4, save=save, split=split))  # finetune's defaults (--nearest 6, encoder + appearance)


def scene_row(name: str, mesh: Path, out: Path) -> dict:
    """The results row of scene ``name`` from its ``curve.json`` (complete, or as far as an interrupted run got)."""
    work = work_dir(name)
    ft = json.loads((work / "curve.json").read_text())
    figures = out / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    for f in ("curve.png", "before_after.png"):
        shutil.copy2(work / f, figures / f"finetune_{slug(name)}_{f}")
    keep = ("seconds", "steps", "psnr", "psnr_masked", "psnr_covered", "coverage", "coverage_masked", "val_psnr",
            "val_psnr_now", "val_psnr_masked", "val_psnr_masked_now", "returned_from")
    mesh = mesh.resolve().relative_to(ROOT) if mesh.resolve().is_relative_to(ROOT) else mesh
    return {"scene": ft["scene"], "mesh": str(mesh), "mesh_made": mesh_record(mesh), "faces": ft["faces"],
            "sources": ft["sources"], "nearest": ft.get("nearest", 0), "val_choice": ft.get("val_choice", "spread"),
            "rays": ft["rays"], "tuned": ft["tuned"], "lr": ft["lr"], "precision": ft["precision"],
            "held_out": ft["held_out"], "split": ft.get("split", "protocol"), "validation_views": ft["validation_views"], "resolution": ft["resolution"],
            "fill": ft["fill"], "curve": [{k: c[k] for k in keep if k in c} for c in ft["curve"]],
            "budget_s": ft["budget_s"], "partial": bool(ft.get("partial")),
            "gain_db": ft["gain_db"], "clock": ft["clock"], "load_average": ft["provenance"].get("loadavg_1min", os.getloadavg()[0]),
            "objects": ft.get("objects", 0.0), **({"scored_by": ft["scored_by"], "val_guard": ft["val_guard"]}
                                                  if "scored_by" in ft else {}),
            **({"visibility": ft["visibility"]} if "visibility" in ft else {}),
            **{k: ft[k] for k in ("val_each_view", "val_skip") if k in ft},
            **({"render": ft["render"]} if "render" in ft else {}),
            "validation": ft["validation"], **({"cpu_seconds": ft["cpu_seconds"]} if "cpu_seconds" in ft else {}),
            "pictures": {"curve": f"figures/finetune_{slug(name)}_curve.png",
                         "before_after": f"figures/finetune_{slug(name)}_before_after.png"}}


def main(argv: list[str] | None = None) -> dict:
    from omnirecon.engine.checkpoint import fingerprint
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", action="append", required=True, help="NAME=PATH (repeatable)")
    p.add_argument("--mesh", action="append", default=[],
                   help="NAME=MESH.ply, in the scene's input frame; keep it where it persists (outputs/bench/...): "
                        "the JSON names it (default: made from the split's training views, module docstring)")
    p.add_argument("--mesh-note", default="omnirecon mesh --views all (omnirecon-tiny)",
                   help="how the given meshes were made (recorded)")
    p.add_argument("--split", choices=list(SPLIT_SUFFIX), default="protocol",
                   help="the held-out views: the scene's protocol, or the extrapolation split's test views")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--resolution", type=int, default=None)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    p.add_argument("--save", action="store_true", help="keep the tuned checkpoint in outputs/bench/finetune_curves/NAME")
    p.add_argument("--collect", action="store_true",
                   help="do not tune: record each scene's curve.json as it stands (an interrupted run's curve so far)")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    scenes = dict(s.split("=", 1) for s in a.scene)
    meshes = dict(s.split("=", 1) for s in a.mesh)
    file = a.out / "finetune_curves.json"
    for scene_name, path in scenes.items():
        name = scene_name + SPLIT_SUFFIX[a.split]
        given = scene_name in meshes
        mesh = Path(meshes[scene_name]) if given else split_mesh(name, Path(path), a.split, a.resolution, a.threads)
        if not a.collect:
            run_scene(name, Path(path), mesh, a.seconds, a.threads, a.resolution, a.save, a.split)
        row = scene_row(name, mesh, a.out)
        row["mesh_note"] = a.mesh_note if given else (
            "omnirecon mesh --views <the training views> (omnirecon-tiny), made by this bench"
            + (" from the extrapolation split's training views" if a.split == "extrapolation" else ""))
        print(name, [(c["seconds"], round(c["psnr"], 2), round(c["coverage"], 3)) for c in row["curve"]])
        a.out.mkdir(parents=True, exist_ok=True)
        with open(file.with_suffix(".lock"), "w") as lock:  # scenes run in parallel processes
            fcntl.flock(lock, fcntl.LOCK_EX)
            result = json.loads(file.read_text()) if file.is_file() else {"rows": {}}
            result["rows"][name] = row
            result.update(provenance=provenance(seed=0),
                          checkpoint={**fingerprint(ROOT / "checkpoints" / "omnirecon-tiny"), "path": "checkpoints/omnirecon-tiny"})
            write_json(file, result)
    return result
