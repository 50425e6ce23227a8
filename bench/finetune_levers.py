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
    "skip1": {"tune": ("encoder", "appearance"), "rays": 8192, "lr": 5e-4, "skip_nearest": 1},
    "skip2": {"tune": ("encoder", "appearance"), "rays": 8192, "lr": 5e-4, "skip_nearest": 2},
    "skip1_latest": {"tune": ("encoder", "appearance"), "rays": 8192, "lr": 5e-4, "skip_nearest": 1, "val_views": 0},
    "residual": {"tune": ("residual",), "rays": 8192},
    "residual_latest": {"tune": ("residual",), "rays": 8192, "val_views": 0},
    "residual_uniform": {"tune": ("residual",), "rays": 8192, "objects": 0.0},
    "residual_uniform_latest": {"tune": ("residual",), "rays": 8192, "objects": 0.0, "val_views": 0},
}
"""Lever rows: overrides of :class:`~omnirecon.workflows.finetune.FinetuneConfig`."""
LAST_MERGE = "the last merge into this file; each row names the commit it ran at (its own provenance)"
"""The note on a results file's header: rows merged from different runs each keep their own provenance."""
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


def merge(file: Path, key: str, row: dict, started: dict | None = None) -> dict:
    """Merge ``row`` into ``file``'s rows under a lock (rows run in parallel processes). The row keeps its own
    provenance: ``started`` (:func:`omnirecon.provenance.provenance` taken when its run began: a commit made while
    it ran is not its commit), else the provenance now, and the checkpoint's fingerprint. The file's header is the
    last merge's (its note says so): a row's numbers are those of the commit in its own ``provenance``."""
    from omnirecon.engine.checkpoint import fingerprint
    from omnirecon.provenance import provenance

    checkpoint = {**fingerprint(ROOT / "checkpoints" / "omnirecon-tiny"), "path": "checkpoints/omnirecon-tiny"}
    row = {**row, "provenance": row.get("provenance") or started or provenance(seed=0),
           "checkpoint": row.get("checkpoint") or checkpoint}
    file.parent.mkdir(parents=True, exist_ok=True)
    with open(file.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        result = json.loads(file.read_text()) if file.is_file() else {"rows": {}}
        result["rows"][key] = row
        result.update(provenance={**provenance(seed=0), "note": LAST_MERGE}, checkpoint=checkpoint)
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
    from omnirecon.provenance import provenance

    p = scene_parser(__doc__)
    p.add_argument("--mesh-note", default="", help="how the meshes were made (recorded)")
    p.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    p.add_argument("--seconds", type=float, default=60.0)
    a = p.parse_args(argv)
    result = {}
    for name, path, mesh in scenes_and_meshes(a):
        for row in a.rows:
            started = provenance(seed=0)
            r = run_row(name, path, mesh, row, a.seconds, a.threads)
            r["mesh_note"] = a.mesh_note
            print(name, row, f"{r['before']['psnr']:.2f} -> {r['after']['psnr']:.2f} dB, {r['steps']} steps")
            result = merge(a.out / "finetune_levers.json", f"{name}/{row}", r, started)
    return result



def recover_provenance(file: Path) -> dict:
    """Rows merged before rows kept their own provenance: give each the header of the first committed version of
    ``file`` (in this branch's history) that holds the row as it is now, marked ``recovered`` (that header is the
    last merge before that commit: the row ran at its commit or at an earlier one of the same session). Rows
    found in no committed version keep none. ``python -c "from bench.finetune_levers import recover_provenance as
    r; from pathlib import Path; r(Path('bench/results/finetune_levers.json'))"``"""
    import subprocess

    result = json.loads(file.read_text())
    rel = str(file.resolve().relative_to(ROOT))
    log = subprocess.run(["git", "log", "--reverse", "--format=%H", "--", rel], cwd=ROOT, capture_output=True, text=True)
    versions = []
    for sha in log.stdout.split():
        text = subprocess.run(["git", "show", f"{sha}:{rel}"], cwd=ROOT, capture_output=True, text=True).stdout
        if text.strip():
            versions.append((sha, json.loads(text)))
    for key, row in result["rows"].items():
        if row.get("provenance"):
            continue
        for sha, old in versions:
            if old.get("rows", {}).get(key) == row and old.get("provenance"):
                row["provenance"] = {**old["provenance"], "recovered": f"the header of {sha[:12]}, the first commit "
                                     "holding this row as it is: the last merge before it (this row's run, a later one, or an edit of the row)"}
                break
    write_json(file, result)
    return result
