"""Geometry from 3 source views: meshes of the shipped checkpoints and the floor, scored.

    python -m bench geometry                                # omnirecon-tiny, ibrnet-tiny, floor
    python -m bench geometry --models floor --tiny          # a fast subset (tests)

Each model runs ``omnirecon eval --geometry`` with K = 3 under the ``full`` protocols (128-px long
side): on the 10 held-out procedural scenes (sources: 3 evenly spaced pool views; the mesh is scored
against the exact ground-truth mesh, objects only; 2 targets per scene for the render and silhouette
scores, to bound CPU time) and on dtu_scan24 / dtu_scan37 (the paper's sources 23, 24, 33; the
protocol's 8 held-out targets for PSNR and silhouette IoU; no DTU ground-truth point cloud is
available here). The mesh is ``omnirecon mesh``'s protocol: z-depth rendered at the 3 virtually
shifted source views, TSDF fusion at 1/256 of the bounds diagonal, marching cubes, mask and
visibility cleaning. ``seconds`` is images-to-mesh time (encode, render depth, fuse, marching cubes,
clean). Writes ``bench/results/geometry_<model>.json`` and the DTU mesh pictures to
``bench/results/figures/``.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import torch

from omnirecon.data.io import write_json

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
DTU = ["neus_dtu/dtu_scan24", "neus_dtu/dtu_scan37"]
SYNTH_TARGETS = 2
"""Targets per procedural scene (its protocol has 5): render and silhouette scores only; the mesh
and its Chamfer distance do not depend on it."""


def load(model_name: str):
    from omnirecon.engine.checkpoint import fingerprint, load_checkpoint
    from omnirecon.models.registry import build_model

    if model_name == "floor":
        return build_model("floor"), {"name": "floor", "preset": "floor"}
    ckpt = ROOT / "checkpoints" / model_name
    model, meta = load_checkpoint(ckpt)
    return model, {"name": model_name, "preset": meta["preset"], "checkpoint": str(ckpt.relative_to(ROOT)),
                   "step": meta["step"], "cpu_seconds": meta["extra"].get("cpu_s"), "sha256": fingerprint(ckpt)["sha256"]}


def run(model_name: str, results: Path, tiny: bool, threads: int) -> dict:
    from omnirecon.engine.evaluate import evaluate

    torch.set_num_threads(threads)
    model, info = load(model_name)
    out = ROOT / "outputs" / "bench" / f"geometry_{model_name}"
    common = dict(model_info=info, protocol_set="full", geometry=True, cache=ROOT / "outputs" / "cache",
                  progress=not tiny)
    synth = evaluate(model, ["synth:eval"], (3,), out / "synth", synth_count=1 if tiny else 10,
                     max_targets=1 if tiny else SYNTH_TARGETS, **common)
    dtu_paths = [str(SHARED / d) for d in DTU if (SHARED / d).is_dir()] if not tiny else []
    dtu = evaluate(model, dtu_paths, (3,), out / "dtu", **common) if dtu_paths else None
    figures = results / "figures"
    pictures = {}
    for s in (dtu or {}).get("scenes", []):
        src = out / "dtu" / s["name"] / "k3" / "mesh.png"
        if src.is_file():
            figures.mkdir(parents=True, exist_ok=True)
            dest = figures / f"geometry_{model_name}_{s['name']}.png"
            shutil.copy2(src, dest)
            pictures[s["name"]] = str(dest.relative_to(results))
    result = {"model": info, "synth": synth, "dtu": dtu, "pictures": pictures, "synth_targets": SYNTH_TARGETS}
    write_json(results / f"geometry_{model_name}.json", result)
    return result


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", nargs="+", default=["floor", "ibrnet-tiny", "omnirecon-tiny"])
    p.add_argument("--tiny", action="store_true", help="one procedural scene, one target (tests)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    for m in a.models:
        r = run(m, a.out, a.tiny, a.threads)
        g = r["synth"]["means"]["synth"]["3"].get("geometry", {})
        print(m, {k: round(v, 4) for k, v in g.items()})

