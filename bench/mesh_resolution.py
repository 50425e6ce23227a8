"""`omnirecon mesh`'s default resolution: a capture meshed at 128 px vs at its photos' size, scored the same way.

    python -m bench mesh_resolution                                # fern at 128 and at its photos' size
    python -m bench mesh_resolution --scenes fern dtu_scan24 --sides 128 0

Each row is ``omnirecon mesh SCENE --ckpt checkpoints/omnirecon-tiny --views all --resolution S`` as ``reconstruct``
runs it (``--depth auto``; ``S = 0``: the photos' own long side, at most 512, as ``reconstruct``), with the CPU seconds
of this process (1 thread) from reading the images to the written mesh, then scored before tuning like ``omnirecon finetune
--mesh M --nearest 6`` (the curve's first point) at the photos' size (held-out views, at most 4; over the object masks where the scene has
them): whole-image PSNR, PSNR over the pixels the mesh covers, and coverage. Meshes stay under
``outputs/bench/mesh_resolution/``; results go to ``bench/results/mesh_resolution.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
SCENES = {"fern": "llff/fern", "dtu_scan24": "neus_dtu/dtu_scan24"}


def run_row(name: str, side: int) -> dict:
    from omnirecon.engine.scenes import photo_side
    from omnirecon.workflows.finetune import FinetuneConfig, run_finetune
    from omnirecon.workflows.mesh import MeshConfig, run_mesh

    path = SHARED / SCENES[name]
    photo = photo_side(path)
    res = side or photo
    work = ROOT / "outputs" / "bench" / "mesh_resolution" / f"{name}_{res}"
    t = time.process_time()
    made = run_mesh(MeshConfig(scene=path, ckpt=ROOT / "checkpoints" / "omnirecon-tiny", views=("all",),
                               resolution=res, out=(work / "mesh.ply",), threads=1, metrics=False, preview=False))
    mesh_cpu = time.process_time() - t
    ft = run_finetune(FinetuneConfig(ckpt=ROOT / "checkpoints" / "omnirecon-tiny", scene=path, seconds=1.0,
                                     eval_at=(0.0,), clock="cpu", threads=1, mesh=work / "mesh.ply", resolution=photo,
                                     out=work / "finetune", max_held_out=4, save=False))
    first = ft["curve"][0]
    row = {"scene": name, "mesh_side": res, "photo_side": photo, "mesh_resolution": made["resolution"],
           "depth": made["options"]["depth"], "views": len(made["views"]), "faces": made["faces"]["final"],
           "mesh_cpu_seconds": mesh_cpu, "stage_wall_seconds": made["seconds"], "held_out": ft["held_out"],
           "nearest": FinetuneConfig.nearest, "psnr": first["psnr"], "psnr_covered": first.get("psnr_covered"),
           "coverage": first.get("coverage"), "mesh": str((work / "mesh.ply").relative_to(ROOT)),
           "load_average": list(os.getloadavg())}
    if "psnr_masked" in first:
        row["psnr_masked"] = first["psnr_masked"]
    return row


def main(argv: list[str] | None = None) -> dict:
    from omnirecon.data.io import write_json
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["fern"], choices=sorted(SCENES))
    p.add_argument("--sides", nargs="+", type=int, default=[128, 0], help="long sides to mesh at (0: the photos')")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    out_file = a.out / "mesh_resolution.json"
    old = json.loads(out_file.read_text()) if out_file.is_file() else {}
    result = {"provenance": provenance(seed=0), "rows": old.get("rows", [])}
    for name in a.scenes:
        for side in a.sides:
            row = run_row(name, side)
            result["rows"] = [r for r in result["rows"] if (r["scene"], r["mesh_side"]) != (name, row["mesh_side"])]
            result["rows"].append(row)
            print(f"{name} meshed at {row['mesh_side']} px: {row['mesh_cpu_seconds']:.1f} CPU-s, {row['faces']:,} faces, "
                  f"PSNR {row['psnr']:.2f} dB (covered {row['psnr_covered']:.2f}, coverage {row['coverage']:.3f})",
                  flush=True)
            write_json(out_file, result)
    return result
