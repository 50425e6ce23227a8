"""What fine-tuning should tune, and how, decided by measurement: the mesh path's held-out PSNR after 60
CPU-seconds of tuning, one row per lever, on real scenes at the photos' own resolution.

    python -m bench finetune_levers --scene fern=../shared/data/llff/fern --mesh fern=MESH.ply --rows base bf16

Rows (``ROWS``): what is tuned (the 2-D encoder, the appearance branch, per-source exposure), pixels per
step, learning rate and bf16 autocast; everything else is ``finetune``'s default (each pixel's ``--nearest 6``
sources, ``--val-choice``), recorded in the row. Every row is ``omnirecon finetune`` with the same mesh, sources,
validation and held-out views, ``--clock cpu --threads 1`` (other jobs on the machine do not shrink
the budget), scored before and after. Rows can run in separate processes: each merges its result into
``bench/results/finetune_levers.json`` under a file lock.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
from pathlib import Path

import torch

from omnirecon.data.io import write_json

ROOT = Path(__file__).resolve().parents[1]
ROWS = {
    "base": {"tune": ("encoder", "appearance"), "rays": 2048, "lr": 5e-4},
    "rays8k": {"tune": ("encoder", "appearance"), "rays": 8192, "lr": 5e-4},
    "bf16": {"tune": ("encoder", "appearance"), "rays": 8192, "precision": "bf16", "lr": 5e-4},
    "lr2e-3": {"tune": ("encoder", "appearance"), "rays": 8192, "lr": 2e-3},
    "appearance": {"tune": ("appearance",), "rays": 8192, "lr": 5e-4},
    "appearance_lr3e-3": {"tune": ("appearance",), "rays": 8192, "lr": 3e-3},
    "encoder": {"tune": ("encoder",), "rays": 8192, "lr": 5e-4},
    "exposure": {"tune": ("encoder", "appearance", "exposure"), "rays": 8192, "lr": 5e-4},
    "appearance_exposure": {"tune": ("appearance", "exposure"), "rays": 8192, "lr": 3e-3},
    "mixed": {"tune": ("encoder", "appearance"), "rays": 8192, "lr": 5e-4, "step_views": 0},
    "mixed_latest": {"tune": ("encoder", "appearance"), "rays": 8192, "lr": 5e-4, "step_views": 0, "val_views": 0},
    "latest": {"tune": ("encoder", "appearance"), "rays": 8192, "lr": 5e-4, "val_views": 0},
    "mixed_lr2e-4": {"tune": ("encoder", "appearance"), "rays": 8192, "lr": 2e-4, "step_views": 0},
    "uniform": {"tune": ("encoder", "appearance"), "rays": 8192, "lr": 5e-4, "objects": 0.0},
    "uniform_exposure": {"tune": ("encoder", "appearance", "exposure"), "rays": 8192, "lr": 5e-4, "objects": 0.0},
    "mixed_uniform": {"tune": ("encoder", "appearance"), "rays": 8192, "lr": 5e-4, "step_views": 0, "objects": 0.0},
    "mixed_uniform_latest": {"tune": ("encoder", "appearance"), "rays": 8192, "lr": 5e-4, "step_views": 0,
                             "objects": 0.0, "val_views": 0},
}
"""Lever rows: overrides of :class:`~omnirecon.workflows.finetune.FinetuneConfig`."""
KEEP = ("seconds", "steps", "psnr", "psnr_masked", "psnr_covered", "coverage", "coverage_masked", "val_psnr",
        "val_psnr_masked", "returned_from")


def run_row(scene: str, path: Path, mesh: Path, row: str, seconds: float, threads: int) -> dict:
    from omnirecon.workflows.finetune import FinetuneConfig, run_finetune

    work = ROOT / "outputs" / "bench" / "finetune_levers" / f"{scene}_{row}"
    ft = run_finetune(FinetuneConfig(ckpt=ROOT / "checkpoints" / "omnirecon-tiny", scene=path, mesh=mesh, seconds=seconds,
                                     eval_at=(0.0, seconds), clock="cpu", threads=threads, out=work, max_held_out=4,
                                     **ROWS[row]))  # finetune's defaults but the row's settings
    first, last = ft["curve"][0], ft["curve"][-1]
    return {"scene": str(path), "mesh": str(mesh), "row": row, "settings": {k: list(v) if isinstance(v, tuple) else v
                                                                           for k, v in ROWS[row].items()},
            "nearest": ft["nearest"], "val_choice": ft["val_choice"], "sources": ft["sources"],
            "validation_views": ft["validation_views"], "returned_from": ft["returned_from"],
            "resolution": ft["resolution"], "tuned_parameters": ft["tuned_parameters"], "steps": last["steps"],
            "before": {k: first[k] for k in KEEP if k in first}, "after": {k: last[k] for k in KEEP if k in last},
            "gain_db": last["psnr"] - first["psnr"],
            **({"gain_masked_db": last["psnr_masked"] - first["psnr_masked"]} if "psnr_masked" in last else {}),
            "visibility": ft.get("visibility", False), "load_average": os.getloadavg()[0]}


def merge(file: Path, key: str, row: dict) -> dict:
    """Merge ``row`` into ``file``'s rows under a lock (rows run in parallel processes); with the provenance
    and the checkpoint's fingerprint."""
    from omnirecon.engine.checkpoint import fingerprint
    from omnirecon.provenance import provenance

    file.parent.mkdir(parents=True, exist_ok=True)
    with open(file.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        result = json.loads(file.read_text()) if file.is_file() else {"rows": {}}
        result["rows"][key] = row
        result.update(provenance=provenance(seed=0), checkpoint={**fingerprint(ROOT / "checkpoints" / "omnirecon-tiny"),
                                                                 "path": "checkpoints/omnirecon-tiny"})
        write_json(file, result)
    return result


def scene_parser(doc: str) -> argparse.ArgumentParser:
    """The options every fine-tuning benchmark takes: scenes and their meshes, threads, the results folder."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--scene", action="append", required=True, help="NAME=PATH (repeatable)")
    p.add_argument("--mesh", action="append", required=True, help="NAME=MESH.ply, in the scene's input frame")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    return p


def scenes_and_meshes(a: argparse.Namespace) -> list[tuple[str, Path, Path]]:
    """``(name, scene folder, mesh file)`` per ``--scene``; sets the torch threads."""
    torch.set_num_threads(a.threads)
    meshes = dict(s.split("=", 1) for s in a.mesh)
    return [(name, Path(path), Path(meshes[name])) for name, path in (s.split("=", 1) for s in a.scene)]


def main(argv: list[str] | None = None) -> dict:
    p = scene_parser(__doc__)
    p.add_argument("--mesh-note", default="", help="how the meshes were made (recorded)")
    p.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    p.add_argument("--seconds", type=float, default=60.0)
    a = p.parse_args(argv)
    result = {}
    for name, path, mesh in scenes_and_meshes(a):
        for row in a.rows:
            r = run_row(name, path, mesh, row, a.seconds, a.threads)
            r["mesh_note"] = a.mesh_note
            print(name, row, f"{r['before']['psnr']:.2f} -> {r['after']['psnr']:.2f} dB, {r['steps']} steps")
            result = merge(a.out / "finetune_levers.json", f"{name}/{row}", r)
    return result

