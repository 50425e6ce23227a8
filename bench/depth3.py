"""Depth from 3 source views on real scenes never trained on (issue 26, goal 3): a model against the plane-sweep
floor, by the two measures the goal names.

    python -m bench depth3                                    # floor and omnirecon-tiny on fern, dtu_scan24/37
    python -m bench depth3 --models floor omnirecon-tiny ibrnet-tiny

* **Agreement with confident stereo depth** at the protocol's held-out targets (``full`` protocols, 128-px long
  side): each target's depth rendered from its K = 3 protocol sources (DTU: the fixed 23, 24, 33), compared where
  classical stereo (``omnirecon.mesh.stereo``, SGBM among every view of the scene, the target's own photo included:
  it is the reference here, never a model input) has at least 2 agreeing pairs. ``abs_rel`` (mean |p - s| / s),
  ``within5`` (max(p/s, s/p) < 1.05) and ``within25`` (the usual delta1, < 1.25) over the pixels both have;
  ``coverage``: the fraction of confident stereo pixels the model gives a depth (opacity >= 0.5; the floor: at least
  2 views agree).
* **Mesh silhouette IoU** (DTU, the object masks): ``omnirecon mesh``'s protocol from the 3 sources (as ``omnirecon
  eval --geometry``), scored on the same targets.

Every model renders with its checkpoint's own render options (omnirecon-tiny: the coarse pass). Writes
``bench/results/depth3.json`` (provenance header, process CPU seconds per model, load average).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
SCENES = ["llff/fern", "neus_dtu/dtu_scan24", "neus_dtu/dtu_scan37"]
K = 3


def agreement(pred: np.ndarray, ok: np.ndarray, stereo: np.ndarray) -> dict:
    """Depth agreement of ``pred`` (valid where ``ok``) with ``stereo`` (0 = not confident). ``# [H, W]`` each."""
    has = stereo > 0
    both = has & ok & (pred > 0) & np.isfinite(pred)
    if not both.any():
        return {"abs_rel": float("nan"), "within5": float("nan"), "within25": float("nan"), "coverage": 0.0,
                "pixels": 0}
    p, s = pred[both], stereo[both]
    ratio = np.maximum(p / s, s / p)
    return {"abs_rel": float((np.abs(p - s) / s).mean()), "within5": float((ratio < 1.05).mean()),
            "within25": float((ratio < 1.25).mean()), "coverage": float(both.sum() / has.sum()),
            "pixels": int(both.sum())}


def stereo_reference(scene, targets: list[int]) -> np.ndarray:
    """Confident stereo z-depth at ``targets`` (0 elsewhere), matched among every view. ``# [T, H, W]``"""
    from omnirecon.mesh.stereo import stereo_depths

    views = list(range(len(scene)))
    out = stereo_depths(scene.images, scene.cameras, views, scene.bounds)
    depth = torch.where(out["confidence"] >= 1.0, out["depth"], torch.zeros(()))
    return depth[targets].numpy()


def score_scene(model, es, ref: np.ndarray) -> dict:
    from omnirecon.cameras import closest_point_to_axes
    from omnirecon.engine.evaluate import geometry_sources
    from omnirecon.engine.protocols import targets_and_pool
    from omnirecon.engine.views import select_sources, view_metric
    from omnirecon.mesh import geometry as geo
    from omnirecon.mesh.build import MeshOptions, mesh_from_model
    from omnirecon.mesh.depth import depth_from_outputs
    from omnirecon.rays import Sources

    scene = es.scene
    targets, pool = targets_and_pool(es.protocol, scene)
    fixed = dict(es.protocol.fixed_sources)
    center = closest_point_to_axes(scene.cameras) if view_metric(scene) == "angle" else None
    rows = []
    for t, s_ref in zip(targets, ref):
        src = list(fixed[K]) if K in fixed else select_sources(scene, scene.cameras[t], pool, K, center)
        with torch.no_grad():
            out = model.render_view(model.encode(Sources.from_scene(scene, src)), scene.cameras[t].to(
                dtype=scene.images.dtype), chunk=4096)
        depth, ok = depth_from_outputs(out)
        rows.append({"target": t, "sources": src, **agreement(depth.double().numpy(), ok.numpy(), s_ref)})
    res = {"targets": targets, "views": rows}
    for m in ("abs_rel", "within5", "within25", "coverage"):
        vals = [r[m] for r in rows if r["pixels"]]
        res[m] = float(np.mean(vals)) if vals else float("nan")
    res["stereo_pixels"] = float((ref > 0).mean())
    if scene.masks is not None:  # silhouette IoU of the 3-view mesh against the object masks
        views = geometry_sources(es, K)
        made = mesh_from_model(model, scene, views, MeshOptions(depth="model"), "cpu")
        if len(made.mesh.faces):
            iou = geo.evaluate_mesh(made.mesh, dataclasses.replace(scene, depths=None), targets)["mask_iou"]
            res["mask_iou"], res["mask_iou_against"] = iou["mean"], iou["against"]
        else:
            res["mask_iou"], res["mask_iou_against"] = 0.0, "masks (empty mesh)"
        res["mesh_views"] = views
    return res


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", nargs="+", default=["floor", "omnirecon-tiny"])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "depth3.json")
    a = p.parse_args(argv)
    from omnirecon.data.io import write_json
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.engine.protocols import targets_and_pool
    from omnirecon.engine.scenes import prepare_scenes
    from omnirecon.models.registry import build_model
    from omnirecon.provenance import provenance

    torch.set_num_threads(a.threads)
    scenes = prepare_scenes([SHARED / s for s in SCENES if (SHARED / s).is_dir()], protocol_set="full")
    cpu0 = time.process_time()
    refs = {es.name: stereo_reference(es.scene, targets_and_pool(es.protocol, es.scene)[0]) for es in scenes}
    stereo_s = time.process_time() - cpu0
    models = {}
    for name in a.models:
        if name == "floor":
            model, info = build_model("floor"), {"name": "floor"}
        else:
            model, meta = load_checkpoint(ROOT / "checkpoints" / name)
            info = {"name": name, "checkpoint": f"checkpoints/{name}", "step": meta["step"],
                    "render_options": {k: v for k, v in meta["model_config"].items()
                                       if k in ("render_fine_pass", "leftover", "forward_box", "samples")}}
        model.eval()
        cpu0 = time.process_time()
        per = {es.name: score_scene(model, es, refs[es.name]) for es in scenes}
        models[name] = {**info, "scenes": per, "cpu_s": time.process_time() - cpu0}
        print(name, {s: {k: round(r[k], 3) for k in ("abs_rel", "within5", "coverage", "mask_iou") if k in r}
                     for s, r in per.items()}, flush=True)
    write_json(a.out, {"provenance": provenance(0, threads=a.threads, load_average=os.getloadavg()),
                       "protocol_set": "full", "k": K, "stereo_cpu_s": stereo_s, "models": models})
    print(f"wrote {a.out}")

