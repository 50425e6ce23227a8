"""Geometry from 3 source views: meshes of the shipped checkpoints, the floor and classical stereo, scored.

    python -m bench geometry                                # floor, stereo, ibrnet-tiny, omnirecon-tiny
    python -m bench geometry --models stereo floor --tiny   # a fast subset (tests)

Each model runs ``omnirecon eval --geometry`` with K = 3 under the ``full`` protocols (128-px long
side): on the 10 held-out procedural scenes (sources: 3 evenly spaced pool views; the mesh is scored
against the exact ground-truth mesh, objects only; 2 targets per scene for the render and silhouette
scores, to bound CPU time) and on dtu_scan24 / dtu_scan37 (the paper's sources 23, 24, 33; the
protocol's 8 held-out targets for PSNR and silhouette IoU; no DTU ground-truth point cloud is
available here). The mesh is ``omnirecon mesh --masks``'s pipeline with its default ``fit`` settings
(:class:`omnirecon.mesh.build.MeshOptions`, recorded in the results): depth at the 3 source views
(the model's fine-pass depth; ``stereo``: OpenCV SGBM on rectified pairs among the same 3 views, no
model), confidence-weighted TSDF fusion, marching cubes, mask and visibility cleaning, face budget,
completion, with the object masks (:data:`MASKS`). ``stereo`` renders no target, so it has no PSNR. ``seconds`` is images-to-mesh time (encode,
depth, fuse, marching cubes, clean, complete); ``cpu_seconds`` splits each row's process CPU time into
target renders (PSNR), the depth source, fusion to completion, scoring and writing.

Meshes go to ``outputs/bench/geometry/<model>/{synth,dtu}/<scene>/k3/mesh.ply`` (the results name them);
the JSON to ``bench/results/geometry_<model>.json``; the DTU mesh pictures (the only ones the section
shows, so only they are drawn) to ``bench/results/figures/``.
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
NO_MODEL = ("stereo",)
"""Rows whose depth source needs no model (nothing rendered at the targets)."""
MASKS = True
"""Mesh with the object masks and score objects only, the section's protocol since it began (VolRecon cleans
with the source masks; the mesh-path section reuses these meshes as object meshes). ``evaluate``'s and
``omnirecon mesh``'s default is the whole scene: since the one mesh pipeline (e797ba0) the bench took that
default silently, which moved the numbers (dtu_scan24 floor IoU 0.44 -> 0.70)."""
SYNTH_TARGETS = 2
"""Targets per procedural scene (its protocol has 5): render and silhouette scores only; the mesh
and its Chamfer distance do not depend on it."""


def load(model_name: str):
    from omnirecon.engine.checkpoint import fingerprint, load_checkpoint
    from omnirecon.models.registry import build_model

    if model_name in NO_MODEL:
        return None, {"name": model_name, "preset": None, "depth": model_name}
    if model_name == "floor":
        return build_model("floor"), {"name": "floor", "preset": "floor"}
    ckpt = ROOT / "checkpoints" / model_name
    model, meta = load_checkpoint(ckpt)
    return model, {"name": model_name, "preset": meta["preset"], "checkpoint": str(ckpt.relative_to(ROOT)),
                   "step": meta["step"], "cpu_seconds": meta["extra"].get("cpu_s"), "sha256": fingerprint(ckpt)["sha256"]}


def mesh_options(model_name: str):
    """The mesh settings of a row: ``omnirecon mesh``'s defaults with the row's depth source."""
    from omnirecon.mesh.build import MeshOptions

    return MeshOptions(depth="stereo" if model_name == "stereo" else "model")


def run(model_name: str, results: Path, tiny: bool, threads: int) -> dict:
    import time

    from omnirecon.engine.evaluate import evaluate

    torch.set_num_threads(threads)
    cpu_start = time.process_time()
    model, info = load(model_name)
    out = (results / "geometry_meshes" if tiny else ROOT / "outputs" / "bench" / "geometry") / model_name  # tests: not ours
    common = dict(model_info=info, protocol_set="full", geometry=True, cache=ROOT / "outputs" / "cache",
                  progress=not tiny, mesh_options=mesh_options(model_name), mesh_masks=MASKS)
    synth = evaluate(model, ["synth:eval"], (3,), out / "synth", synth_count=1 if tiny else 10,
                     max_targets=1 if tiny else SYNTH_TARGETS, mesh_pictures=False, **common)
    dtu_paths = [str(SHARED / d) for d in DTU if (SHARED / d).is_dir()] if not tiny else []
    dtu = evaluate(model, dtu_paths, (3,), out / "dtu", **common) if dtu_paths else None
    figures = results / "figures"
    pictures, meshes = {}, {}
    for part, res in (("synth", synth), ("dtu", dtu)):
        for s in (res or {}).get("scenes", []):
            ply = out / part / s["name"] / "k3" / "mesh.ply"
            if ply.is_file():
                meshes[s["name"]] = str(ply.relative_to(ROOT) if ply.is_relative_to(ROOT) else ply)
            src = ply.with_name("mesh.png")
            if part == "dtu" and src.is_file():
                figures.mkdir(parents=True, exist_ok=True)
                dest = figures / f"geometry_{model_name}_{s['name']}.png"
                shutil.copy2(src, dest)
                pictures[s["name"]] = str(dest.relative_to(results))
    result = {"model": info, "synth": synth, "dtu": dtu, "pictures": pictures, "meshes": meshes,
              "synth_targets": SYNTH_TARGETS, "cpu_seconds": cpu_parts([synth, dtu], time.process_time() - cpu_start)}
    write_json(results / f"geometry_{model_name}.json", result)
    return result


def cpu_parts(runs: list[dict | None], total: float) -> dict:
    """Process CPU seconds of one row by part: target renders (PSNR), the depth source, fusion to completion,
    mesh scoring, writing (mesh files, pictures), and the rest (loading, scene preparation, target scoring)."""
    views = [v for r in runs if r for s in r["scenes"] for st in s["settings"].values() for v in st["views"]]
    geo = [st["geometry"] for r in runs if r for s in r["scenes"] for st in s["settings"].values() if "geometry" in st]
    parts = {"target_renders": sum(v.get("cpu_seconds", 0.0) for v in views)}
    for key in ("depth", "mesh", "score", "write"):
        parts[key] = sum(g.get("cpu_seconds", {}).get(key, 0.0) for g in geo)
    parts["other"] = total - sum(parts.values())
    parts["total"] = total
    return parts


def speed_ab(rows: list[str], results: Path) -> dict:
    """What this section's two speed changes save, measured on the meshes a full run kept (process CPU seconds,
    one process, old and new side by side): the picture of each procedural mesh (drawn before, not shown by the
    section, no longer drawn) and the Chamfer search without and with the bound at the cap (the results must
    be identical, and are checked to be). Writes ``geometry_speed.json``."""
    import time

    import numpy as np

    from omnirecon.engine.scenes import prepare_scenes
    from omnirecon.mesh import geometry as geo
    from omnirecon.mesh.files import read_mesh
    from omnirecon.provenance import provenance

    torch.set_num_threads(1)
    scenes = {es.name: es.scene for es in prepare_scenes(["synth:eval"], 10, ROOT / "outputs" / "cache", None, "full")}
    out = {"provenance": provenance(), "rows": {}}
    for row in rows:
        folder = ROOT / "outputs" / "bench" / "geometry" / row / "synth"
        t = {"picture": 0.0, "chamfer_unbounded": 0.0, "chamfer_bounded": 0.0, "scenes": 0}
        for name, scene in scenes.items():
            ply = folder / name / "k3" / "mesh.ply"
            if not ply.is_file():
                continue
            mesh = read_mesh(ply, scene.to_input)
            cam = scene.cameras[0]
            c0 = time.process_time()
            geo.shaded_image(mesh, cam.rescaled(max(1.0, 512 / max(cam.width, cam.height))))
            c1 = time.process_time()
            scales = geo.scene_scales(scene)
            gt = geo.sample_points(geo.ground_truth_mesh(scene), 100_000, 1)
            gt = gt[geo.observed(gt, scene)]
            pred = geo.sample_points(mesh, 100_000, 0)
            lo, hi = scene.bounds.double().numpy() + np.array([[-1.0], [1.0]]) * scales["max_dist"]
            pred = pred[((pred >= lo) & (pred <= hi)).all(1)]
            c2 = time.process_time()
            d_acc, d_comp = geo.nearest_distances(pred, gt), geo.nearest_distances(gt, pred)  # the old search
            c3 = time.process_time()
            new = geo.chamfer_fscore(pred, gt, scales["threshold"], scales["max_dist"])
            c4 = time.process_time()
            cap = scales["max_dist"]
            same = all(np.isclose(new[k], v) or new[k] == v for k, v in {
                "accuracy": float(d_acc[d_acc < cap].mean()) if (d_acc < cap).any() else float("inf"),
                "completeness": float(d_comp[d_comp < cap].mean()) if (d_comp < cap).any() else float("inf"),
                "precision": float((d_acc < scales["threshold"]).mean()) if len(d_acc) else 0.0,
                "completeness_dropped": float((d_comp >= cap).mean())}.items())
            if not same:
                raise AssertionError(f"bounded Chamfer search differs on {row} {name}")
            t["picture"] += c1 - c0
            t["chamfer_unbounded"] += c3 - c2
            t["chamfer_bounded"] += c4 - c3
            t["scenes"] += 1
        out["rows"][row] = t
        print(row, {k: round(v, 2) for k, v in t.items()})
    write_json(results / "geometry_speed.json", out)
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", nargs="+", default=["floor", "stereo", "ibrnet-tiny", "omnirecon-tiny"])
    p.add_argument("--tiny", action="store_true", help="one procedural scene, one target (tests)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    p.add_argument("--speed-ab", action="store_true", help="time the speed changes on the kept meshes of --models")
    a = p.parse_args(argv)
    if a.speed_ab:
        speed_ab(a.models, a.out)
        return
    for m in a.models:
        r = run(m, a.out, a.tiny, a.threads)
        g = r["synth"]["means"]["synth"]["3"].get("geometry", {})
        print(m, {k: round(v, 4) for k, v in g.items()})
        print(m, "CPU-s", {k: round(v, 1) for k, v in r["cpu_seconds"].items()})

