"""Where the demo's mesh loses depth: each stage of the mesh pipeline against the exact depth, per region.

    python -m bench depth_regions                    # stereo+model, the default match grid (~1 CPU-min)
    python -m bench depth_regions --match-side 0     # stereo matched on the photos' own 128-px grid
    python -m bench depth_regions --occlusion 0      # no visibility check before fusion
    python -m bench depth_regions --fill-holes 0     # fusion's holes left open (only marching cubes' pinholes closed)
    python -m bench depth_regions --refine none      # no photometric refinement of the stereo maps

On the demo's procedural scene (``bench/depth_sources.py``: seed 900999, 24 views at 128 px, the 18
training views meshed) every training view's depth after each stage is compared with the exact depth,
split by the scene's labels into regions (the dark sphere, the box, the green object, the other objects,
the ground, the sky):

* ``stereo``: the voted stereo maps (:mod:`omnirecon.mesh.stereo`), before any confidence;
* ``stereo refined``: the same after the photometric refinement (:mod:`omnirecon.mesh.stereo_refine`);
* ``stereo+model``: the maps fusion gets (stereo where it matched, the model's coarse depth for the rest);
* the mesh after each stage (``marching_cubes`` = fusion, ``visible`` / ``components`` = cleaning,
  ``decimated`` = face budget, ``completed`` = completion), rendered at the training views.

Per region: coverage (pixels with depth), abs-rel, the share of pixels > 5 % off, of those the share in
front of (``near``) and behind (``far``) the exact surface, and at the region's 2-px edge and interior.
Sky: the share of pixels with any depth. Also the held-out mesh path per region (:func:`held_out_psnr`:
the completed mesh and the exact mesh, the protocol's held-out views from the default 3 sources, with and
without the renderer's occlusion test). Writes ``bench/results/depth_regions.json``.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch

from omnirecon.data.io import write_json

REGIONS = {"sphere": [5], "box": [6], "green object": [1], "other objects": [2, 3, 4], "ground": [255], "sky": [0]}
"""The demo scene's label ids per region (``scene.json``: 5 sphere, 6 box, 1 the green cylinder)."""


def region_scores(depth: np.ndarray, exact: np.ndarray, labels: np.ndarray) -> dict:
    """``depth`` against ``exact`` (``# [N, H, W]``, 0 = none) per region of ``labels``."""
    from scipy.ndimage import binary_erosion

    out = {}
    for name, ids in REGIONS.items():
        m = np.isin(labels, ids)
        if name == "sky":
            out[name] = {"pixels": int(m.sum()), "with_depth": float((depth[m] > 0).mean())}
            continue
        inner = np.stack([binary_erosion(x, iterations=2) for x in m])
        row = {"pixels": int(m.sum())}
        for part, sel in (("all", m), ("edge", m & ~inner), ("interior", inner)):
            has = sel & (depth > 0)
            rel = (depth[has] - exact[has]) / exact[has]
            row[part] = {"coverage": float(has.sum() / max(1, sel.sum())),
                         "abs_rel": float(np.abs(rel).mean()) if len(rel) else None,
                         "outliers": float((np.abs(rel) > 0.05).mean()) if len(rel) else None,
                         "near": float((rel < -0.05).mean()) if len(rel) else None,
                         "far": float((rel > 0.05).mean()) if len(rel) else None}
        out[name] = row
    return out


def held_out_psnr(model, scene, targets: list[int], meshes: dict) -> dict:
    """PSNR of the mesh path at ``targets`` per region (``REGIONS``) and over the whole image, for each of
    ``meshes`` (scene frame), with the occlusion test off and on (``MeshRenderOptions.visibility``)."""
    from omnirecon.engine.views import default_views
    from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions
    from omnirecon.rays import Sources

    sources = Sources.from_scene(scene, default_views(scene, 3))
    gts = [scene.images[t].float().numpy() for t in targets]
    out = {}
    for name, mesh in meshes.items():
        for vis in (False, True):
            opts = MeshRenderOptions(background=tuple(scene.background), visibility=vis, fill="background",
                                     cull_back_faces=False)
            with MeshRenderer(model, mesh, sources, opts) as r:
                imgs = [r.render(scene.cameras[t])["rgb"].float().clamp(0, 1).numpy() for t in targets]
            row = {}
            for region, ids in {"whole image": None, **REGIONS}.items():
                vals = []
                for img, gt, t in zip(imgs, gts, targets):
                    m = np.ones(gt.shape[:2], bool) if ids is None else np.isin(scene.labels[t].numpy(), ids)
                    vals.append(-10 * np.log10(max(float(((img - gt) ** 2)[m].mean()), 1e-10)))
                row[region] = float(np.mean(vals))
            out[f"{name}, occlusion test {'on' if vis else 'off'}"] = row
    return out


def main(argv: list[str] | None = None) -> dict:
    from bench.depth_sources import ROOT, held_out, load
    from omnirecon.engine.checkpoint import fingerprint, load_checkpoint
    from omnirecon.mesh.build import MeshOptions, depth_maps, mesh_from_depths, refined
    from omnirecon.mesh.complete import DepthRenderer
    from omnirecon.mesh.depth import oracle_depths, stereo_maps
    from omnirecon.mesh.stereo import StereoOptions
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--match-side", type=int, default=StereoOptions.match_side,
                   help="StereoOptions.match_side (0: the photos' own grid)")
    p.add_argument("--occlusion", type=int, default=MeshOptions.occlusion,
                   help="MeshOptions.occlusion (0: no visibility check before fusion)")
    p.add_argument("--fill-holes", type=int, default=MeshOptions.fill_holes,
                   help="MeshOptions.fill_holes (0: fusion's holes left open)")
    p.add_argument("--refine", default=MeshOptions.refine, choices=("none", "stereo", "all"),
                   help="MeshOptions.refine (none: no photometric refinement of the stereo maps)")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.process_time()
    path, scene, proto, res = load("demo", False)
    targets, views = held_out(scene, proto)
    labels = scene.labels[views].numpy()
    exact = oracle_depths(scene, views).depth.numpy()
    ckpt = ROOT / "checkpoints" / "omnirecon-tiny"
    model = load_checkpoint(ckpt)[0]
    opts = MeshOptions(depth="stereo+model", depth_pass="coarse", stereo=StereoOptions(match_side=a.match_side),
                       occlusion=a.occlusion, fill_holes=a.fill_holes, refine=a.refine)
    voted = stereo_maps(scene, views, opts.stereo)
    stages = {"stereo": region_scores(voted.depth.numpy(), exact, labels)}
    if a.refine != "none":
        stages["stereo refined"] = region_scores(refined(voted, scene, opts).depth.numpy(), exact, labels)
    maps = depth_maps(opts, scene, views, model)
    stages["stereo+model"] = region_scores(maps.depth.numpy(), exact, labels)
    meshes: dict = {}
    mesh_from_depths(maps, scene, views, opts, None, stages=meshes)
    for name, mesh in meshes.items():
        r = DepthRenderer(mesh)
        d = np.stack([r(scene.cameras[v]) for v in views])
        r.close()
        stages[name] = region_scores(d, exact, labels)
    from omnirecon.mesh.geometry import ground_truth_mesh

    psnr = held_out_psnr(model, scene, targets, {"exact mesh": ground_truth_mesh(scene), "completed": meshes["completed"]})
    result = {"provenance": provenance(seed=0), "checkpoint": {**fingerprint(ckpt), "path": "checkpoints/omnirecon-tiny"},
              "scene": "demo", "views": views, "match_side": a.match_side, "occlusion": a.occlusion,
              "fill_holes": a.fill_holes, "refine": a.refine, "stages": stages,
              "held_out": targets, "held_out_psnr": psnr, "cpu_seconds": time.process_time() - t0, "load_average": list(os.getloadavg())}
    name = "depth_regions.json" if a.match_side == StereoOptions.match_side else f"depth_regions_match{a.match_side}.json"
    if a.occlusion != MeshOptions.occlusion:
        name = name.replace(".json", f"_occlusion{a.occlusion}.json")
    if a.fill_holes != MeshOptions.fill_holes:
        name = name.replace(".json", f"_fill{a.fill_holes}.json")
    if a.refine != MeshOptions.refine:
        name = name.replace(".json", f"_refine_{a.refine}.json")
    write_json(a.out / name, result)
    for stage, regions in stages.items():
        print(f"{stage:14s} " + " | ".join(
            f"{k} {v['all']['outliers']:.3f}" if "all" in v else f"{k} {v['with_depth']:.3f}" for k, v in regions.items()))
    for name, row in psnr.items():
        print(f"{name:34s} " + " | ".join(f"{k} {v:.2f}" for k, v in row.items()))
    return result
