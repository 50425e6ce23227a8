"""The mesh path's PSNR against seconds of CPU tuning, with coverage, on real and procedural scenes.

    python -m bench finetune_curves --scene fern=../shared/data/llff/fern --mesh fern=MESH.ply
    python -m bench finetune_curves --scene demo=PATH --mesh demo=MESH.ply --seconds 300

Per scene: ``omnirecon finetune`` of the 2-D encoder and the appearance branch with the given mesh
(the project's own ``omnirecon mesh --views all`` meshes; the JSON records which), images at the
protocol's 128-px long side, the clock this process's CPU time (``--clock cpu``: other jobs on the
machine do not shrink the budget), scored on the protocol's held-out views at 0, 10, 30, 60 (and 300)
s. The returned state is the best on validation views (never sources, never held-out views), so the
held-out curve is what a user gets when tuning stops at that time. Each run merges its scene into
``bench/results/finetune_curves.json`` (scenes can run in separate processes) and copies the curve
and the before/after picture to ``bench/results/figures/``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

import torch

from omnirecon.data.io import write_json

ROOT = Path(__file__).resolve().parents[1]
TIMES = (0.0, 10.0, 30.0, 60.0)


def run_scene(name: str, path: Path, mesh: Path, seconds: float, out: Path, threads: int, resolution: int | None) -> dict:
    from omnirecon.workflows.finetune import FinetuneConfig, run_finetune

    times = tuple(t for t in (*TIMES, 300.0) if t <= seconds)
    work = ROOT / "outputs" / "bench" / "finetune_curves" / name
    ft = run_finetune(FinetuneConfig(ckpt=ROOT / "checkpoints" / "omnirecon-tiny", scene=path, mesh=mesh,
                                     seconds=seconds, eval_at=times, clock="cpu", threads=threads, out=work,
                                     resolution=resolution, max_held_out=4))
    figures = out / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    for f in ("curve.png", "before_after.png"):
        shutil.copy2(work / f, figures / f"finetune_{name}_{f}")
    keep = ("seconds", "steps", "psnr", "psnr_masked", "psnr_covered", "coverage", "coverage_masked", "val_psnr",
            "val_psnr_now", "returned_from")
    return {"scene": str(path), "mesh": str(mesh), "faces": ft["faces"], "sources": ft["sources"],
            "held_out": ft["held_out"], "validation_views": ft["validation_views"], "resolution": ft["resolution"],
            "fill": ft["fill"], "curve": [{k: c[k] for k in keep if k in c} for c in ft["curve"]],
            "gain_db": ft["gain_db"], "clock": ft["clock"], "load_average": os.getloadavg()[0],
            "pictures": {"curve": f"figures/finetune_{name}_curve.png",
                         "before_after": f"figures/finetune_{name}_before_after.png"}}


def main(argv: list[str] | None = None) -> dict:
    from omnirecon.engine.checkpoint import fingerprint
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", action="append", required=True, help="NAME=PATH (repeatable)")
    p.add_argument("--mesh", action="append", required=True, help="NAME=MESH.ply, in the scene's input frame")
    p.add_argument("--mesh-note", default="omnirecon mesh --views all (omnirecon-tiny)",
                   help="how the meshes were made (recorded)")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--resolution", type=int, default=None)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    scenes = dict(s.split("=", 1) for s in a.scene)
    meshes = dict(s.split("=", 1) for s in a.mesh)
    file = a.out / "finetune_curves.json"
    for name, path in scenes.items():
        row = run_scene(name, Path(path), Path(meshes[name]), a.seconds, a.out, a.threads, a.resolution)
        row["mesh_note"] = a.mesh_note
        print(name, [(c["seconds"], round(c["psnr"], 2), round(c["coverage"], 3)) for c in row["curve"]])
        result = json.loads(file.read_text()) if file.is_file() else {"rows": {}}
        result["rows"][name] = row
        result.update(provenance=provenance(seed=0), checkpoint={**fingerprint(ROOT / "checkpoints" / "omnirecon-tiny"),
                                                                 "path": "checkpoints/omnirecon-tiny"})
        write_json(file, result)
    return result

