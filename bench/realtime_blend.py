"""Real-time mesh path against finetune's scores: the held-out views rendered frame by frame, old and new blend.

    python -m bench realtime_blend                     # dtu_scan37, dtu_scan24, fern
    python -m bench realtime_blend --scenes dtu_scan37 --out outputs/bench/rt

Per scene, the mesh and the ``finetune`` record (``curve.json``) a ``python -m bench depth_sources`` row wrote
(``--rows``' default: the scene's default-scoring row, a mesh from every training view), then each of finetune's
held-out views rendered by :class:`omnirecon.mesh.ibr.MeshRenderer`'s frame path (``render(extras=False)``, what
videos, ``render --mesh`` and the viewer's Python twin draw), each frame from its own nearest training views:

* ``before``: the real-time path before session 16: 3 sources per frame (``reconstruct``'s ``--num-views``), the
  angle blend's 6 sources per point, no source masks (the per-scene blend and fill as ``scene_defaults``);
* ``finetune``: :func:`omnirecon.mesh.ibr.realtime_setting` of the record: the sources per frame finetune scored
  with (``--nearest``), the angle sources it chose on its validation views, its source masks.
* ``every_source`` (the angle blend, when the record's sources per frame are fewer than the training views): the same
  with every training view a source of every frame, as finetune's angle blend picks each point's nearest among all.

Held-out PSNR (whole image; over the object masks on DTU) beside the record's own score of the same views, and the
CPU milliseconds per frame (this process, 1 thread, after one warm-up frame; ratios within one run compare).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from omnirecon.data.io import write_json

ROOT = Path(__file__).resolve().parents[1]
ROWS = {"dtu_scan37": "stereo_fill_nearest_6_all_views_angle_blend_nearest_fill_angle_auto",
        "dtu_scan24": "stereo_fill_nearest_6_all_views_angle_blend_nearest_fill_angle_auto",
        "fern": "stereo_fill_nearest_6"}
"""The depth_sources row (its folder under outputs/bench/depth_sources) whose mesh and finetune record each scene
uses: the scene's default scoring."""


def render_views(model, mesh, scene, targets: list[int], pool: list[int], setting: dict) -> dict:
    """Held-out PSNR (and over the masks) and CPU ms per frame of the real-time path under ``setting``."""
    from omnirecon import metrics
    from omnirecon.engine.views import select_sources
    from omnirecon.mesh.ibr import MeshRenderer, realtime_options
    from omnirecon.rays import Sources

    bg = tuple(scene.background) if scene.background is not None else (1.0, 1.0, 1.0)
    psnr, masked, ms = [], [], []
    for t in targets:
        cam = scene.cameras[t].to(dtype=torch.float32)
        picks = sorted(select_sources(scene, cam, pool, setting["sources"] or len(pool)))
        with MeshRenderer(model, mesh, Sources.from_scene(scene, picks),
                          realtime_options(setting, background=bg, visibility=True)) as r:
            r.render(cam, extras=False)  # warm-up
            c0 = time.process_time()
            rgb = r.render(cam, extras=False)["rgb"].float().clamp(0, 1)
            ms.append(1000 * (time.process_time() - c0))
        gt = scene.images[t].float()
        psnr.append(metrics.psnr(rgb, gt))
        if scene.masks is not None:
            masked.append(metrics.psnr(rgb, gt, scene.masks[t].bool()))
    out = {"setting": setting, "psnr": float(np.mean(psnr)), "per_view": [round(p, 3) for p in psnr],
           "cpu_ms_per_frame": float(np.median(ms))}
    if masked:
        out["psnr_masked"] = float(np.mean(masked))
        out["per_view_masked"] = [round(p, 3) for p in masked]
    return out


def mesh_of(name: str, folder: Path) -> Path:
    """The mesh a depth_sources row scored: its folder's ``mesh.ply``, or, when rows of one run shared a mesh (it is
    written once, in the first row's folder), the ``mesh_file`` the row recorded in ``bench/results/depth_sources.json``."""
    if (folder / "mesh.ply").is_file():
        return folder / "mesh.ply"
    rows = json.loads((Path(__file__).parent / "results" / "depth_sources.json").read_text())["rows"]
    slug = folder.name[len(name) + 1:]
    for r in rows:
        if r["scene"] == name and "mesh_file" in r and \
                r["source"].replace("+", "_").replace(", ", "_").replace(" ", "_") == slug:
            return ROOT / r["mesh_file"]
    return folder / "mesh.ply"  # read_mesh names the missing file


def run_scene(name: str, folder: Path) -> dict:
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.engine.scenes import load_at_resolution
    from omnirecon.mesh.files import read_mesh
    from omnirecon.mesh.ibr import realtime_setting, scene_defaults

    record = json.loads((folder / "finetune" / "curve.json").read_text())
    scene = load_at_resolution(record["scene"], max(record["resolution"]), "white")
    mesh_file = mesh_of(name, folder)
    mesh = read_mesh(mesh_file, scene.to_input)
    model, _ = load_checkpoint(ROOT / "checkpoints" / "omnirecon-tiny")
    targets, pool = record["held_out"], record["sources"]
    blend, fill = scene_defaults(scene)
    setting = realtime_setting(scene, record)
    before = {"blend": blend, "fill": fill, "sources": 3, "angle_sources": 6, "source_masks": False}
    row = {"scene": name, "mesh_file": str(mesh_file.relative_to(ROOT)), "held_out": targets,
           "resolution": record["resolution"], "finetune_record": {
               "render": record.get("render"), "psnr": record["curve"][0]["psnr"],
               **({"psnr_masked": record["curve"][0]["psnr_masked"]} if "psnr_masked" in record["curve"][0] else {})},
           "before": render_views(model, mesh, scene, targets, pool, before),
           "finetune": render_views(model, mesh, scene, targets, pool, setting)}
    if setting["blend"] == "angle" and 0 < setting["sources"] < len(pool):  # an older record: also every source
        row["every_source"] = render_views(model, mesh, scene, targets, pool, {**setting, "sources": len(pool)})
    return row


def main(argv: list[str] | None = None) -> dict:
    from bench.depth_rows import row_arguments
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    row_arguments(p, ROWS)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    out_file = a.out / "realtime_blend.json"
    old = json.loads(out_file.read_text()) if out_file.is_file() else {}
    result = {"provenance": provenance(seed=0), "rows": [r for r in old.get("rows", []) if r["scene"] not in a.scenes]}
    for name in a.scenes:
        row = run_scene(name, a.meshes / f"{name}_{ROWS[name]}")
        row["load_average"] = list(os.getloadavg())
        result["rows"].append(row)
        key = "psnr_masked" if "psnr_masked" in row["before"] else "psnr"
        print(f"{name}: finetune scored {row['finetune_record'].get(key):.2f}; real-time " + ", ".join(
            f"{k} {row[k][key]:.2f} ({row[k]['cpu_ms_per_frame']:.0f} CPU-ms)"
            for k in ("before", "finetune", "every_source") if k in row), flush=True)
        write_json(out_file, result)
    return result
