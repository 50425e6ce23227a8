"""Where meshing's time goes: object captures -> mesh, CPU seconds per stage at one thread (issue 24, item 6).

    python -m bench mesh_speed                                   # lego (100 views), fox (58), dtu_scan37 (41)
    python -m bench mesh_speed --scenes lego --views 20          # a subset: 20 evenly spaced meshing views
    python -m bench mesh_speed --scenes dtu_scan37 --out /tmp/ms # results elsewhere (before / after comparisons)

Each row meshes one capture as ``omnirecon mesh --views all`` does at the photos' size (``--depth auto``:
``stereo+model`` with omnirecon-tiny's coarse depth at 128 px on object captures without masks, NeRF-synthetic's lego
on its white background and instant-ngp's fox; ``stereo`` with the object masks on dtu_scan37), from the views
``python -m bench depth_sources`` meshes (every training view but the protocol's held-out ones: lego 100 at 400x400,
fox 58 at 225x400, dtu_scan37 41 at 400x300), from reading the images to the completed mesh, at one torch / OpenCV
thread (``LP_NUM_THREADS=1`` for the GL rasterizer). The stages are the pipeline's own functions, each timed by this
process's CPU clock (``time.process_time`` plus the CPU of finished child processes: pymeshlab's hole closing runs in
one) while it runs, and each charged only for the time outside the other timed functions it calls (so the stages add
up to the total; ``other`` is what no timed function covers). The row keeps a SHA-256 of the mesh (vertices as float64,
faces as int64): two runs with the same hash made the same mesh bit for bit.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
SCENES = {"lego": "blender/lego", "fox": "instant_ngp/fox", "dtu_scan37": "neus_dtu/dtu_scan37"}
MASKED = ("dtu_scan37",)
"""Scenes meshed with their object masks (as ``depth_sources`` meshes DTU)."""
STAGES = (
    # (label, module, function): each charged for its own time, not the timed functions it calls
    ("load", "omnirecon.engine.scenes", "load_at_resolution"),
    ("stereo: SGBM", "omnirecon.mesh.stereo", "match"),
    ("stereo: rectify, read back", "omnirecon.mesh.stereo", "pair_depth"),
    ("stereo: vote", "omnirecon.mesh.stereo", "vote"),
    ("stereo: other", "omnirecon.mesh.stereo", "stereo_depths"),
    ("refine", "omnirecon.mesh.stereo_refine", "refine_depths"),
    ("model depth", "omnirecon.mesh.depth", "model_depths"),
    ("depth: other", "omnirecon.mesh.build", "depth_maps"),
    ("disagreement", "omnirecon.mesh.fusion", "depth_disagreement"),
    ("consistency", "omnirecon.mesh.fusion", "consistency"),
    ("occlusion", "omnirecon.mesh.fusion", "occlusion_votes"),
    ("fusion: band", "omnirecon.mesh.fusion", "surface_band"),
    ("fusion: integrate", "omnirecon.mesh.fusion", "fuse"),
    ("marching cubes", "omnirecon.mesh.fusion", "extract_mesh"),
    ("clean: hidden faces", "omnirecon.mesh.clean", "visible_faces"),
    ("clean: components", "omnirecon.mesh.clean", "drop_small_components"),
    ("clean: other", "omnirecon.mesh.clean", "clean_mesh"),
    ("hull trim", "omnirecon.mesh.clean", "hull_keep"),
    ("hull: restore seen", "omnirecon.mesh.clean", "restore_seen"),
    ("decimate", "omnirecon.mesh.clean", "decimate"),
    ("close holes", "omnirecon.mesh.clean", "close_holes"),
    ("close holes", "omnirecon.mesh.clean", "close_small_holes"),
    ("completion", "omnirecon.mesh.complete", "complete_surface"),
    ("mesh: other", "omnirecon.mesh.build", "mesh_from_depths"),
)


def cpu() -> float:
    """CPU seconds of this process and its finished children."""
    t = os.times()
    return time.process_time() + t.children_user + t.children_system


class StageClock:
    """Exclusive CPU seconds per stage label: a timed function is charged for its time minus that of the timed
    functions it calls."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self.stack: list[list] = []  # [label, start, seconds spent in nested timed calls]

    def wrap(self, label: str, fn):
        def timed(*args, **kwargs):
            self.stack.append([label, cpu(), 0.0])
            try:
                return fn(*args, **kwargs)
            finally:
                _, start, nested = self.stack.pop()
                spent = cpu() - start
                self.seconds[label] = self.seconds.get(label, 0.0) + spent - nested
                self.calls[label] = self.calls.get(label, 0) + 1
                if self.stack:
                    self.stack[-1][2] += spent
        timed.__wrapped__ = fn
        return timed


@contextmanager
def timed_stages(clock: StageClock):
    """Every reference to each :data:`STAGES` function in the package's loaded modules (``from x import f`` copies
    too) replaced by its timed wrapper for the duration."""
    import importlib

    for _, mod, _ in STAGES:
        importlib.import_module(mod)
    importlib.import_module("omnirecon.workflows.mesh")
    swapped = []
    for label, mod, name in STAGES:
        fn = getattr(sys.modules[mod], name)
        wrapper = clock.wrap(label, fn)
        for m in [m for k, m in list(sys.modules.items()) if k.startswith("omnirecon") and m is not None]:
            for attr, value in list(vars(m).items()):
                if value is fn:
                    setattr(m, attr, wrapper)
                    swapped.append((m, attr, fn))
    try:
        yield clock
    finally:
        for m, attr, fn in reversed(swapped):
            setattr(m, attr, fn)


def mesh_hash(mesh) -> str:
    """SHA-256 of the mesh's vertices (float64) and faces (int64), first 16 hex digits."""
    h = hashlib.sha256(np.ascontiguousarray(np.asarray(mesh.vertices, np.float64)).tobytes())
    h.update(np.ascontiguousarray(np.asarray(mesh.faces, np.int64)).tobytes())
    return h.hexdigest()[:16]


def meshing_views(scene, proto, count: int | None) -> list[int]:
    """Every training view but the protocol's held-out ones (``count``: that many of them, evenly spaced)."""
    from omnirecon.engine.protocols import targets_and_pool

    targets, pool = targets_and_pool(proto, scene)
    views = [v for v in pool if v not in set(targets)]
    if count and count < len(views):
        views = [views[i] for i in np.unique(np.linspace(0, len(views) - 1, count).round().astype(int))]
    return views


def run_row(name: str, count: int | None, model, write: Path | None = None) -> dict:
    from omnirecon.data import detect_format
    from omnirecon.engine import scenes
    from omnirecon.engine.protocols import protocol_for
    from omnirecon.mesh.build import MeshOptions, default_depth, mesh_from_model
    from omnirecon.provenance import provenance

    path = SHARED / SCENES[name]
    fmt = detect_format(path)
    proto = protocol_for(path, fmt)
    masks = name in MASKED
    clock = StageClock()
    with timed_stages(clock):
        t0, w0 = cpu(), time.perf_counter()
        scene = scenes.load_at_resolution(path, 512, proto.background, fmt)  # the timed one
        views = meshing_views(scene, proto, count)
        depth = default_depth(scene, True, masks)
        opts = MeshOptions(depth=depth, depth_pass="coarse" if depth == "stereo+model" else "fine")
        made = mesh_from_model(model if depth == "stereo+model" else None, scene, views, opts, use_masks=masks)
        total, wall = cpu() - t0, time.perf_counter() - w0
    stages = dict(clock.seconds)
    stages["other"] = total - sum(stages.values())
    if write is not None:
        made.mesh.export(write / f"{name}_{len(views)}.ply")
    src = made.info["depth_source"]
    stereo_info = next((p for p in src.get("parts", [src]) if p.get("source") == "stereo"), None)
    return {"scene": name, "commit": provenance()["commit"], "depth": depth, "masks": masks, "views": len(views), "resolution": [scene.width, scene.height],
            "cpu_seconds": total, "wall_seconds": wall, "stage_cpu_seconds": stages, "calls": clock.calls,
            "per_view_cpu_seconds": total / len(views), "faces": len(made.mesh.faces),
            "vertices": len(made.mesh.vertices), "mesh_sha256": mesh_hash(made.mesh), "voxel": made.info["voxel"],
            "grid": made.info["grid"], "face_counts": made.info["faces"],
            "stereo_pairs": None if stereo_info is None else sum(len(p) for p in stereo_info["pairs"]),
            "load_average": list(os.getloadavg())}


def print_row(row: dict) -> None:
    print(f"{row['scene']} ({row['views']} views {row['resolution'][0]}x{row['resolution'][1]}, {row['depth']}"
          f"{', masks' if row['masks'] else ''}): {row['cpu_seconds']:.1f} CPU-s "
          f"({row['per_view_cpu_seconds']:.2f} per view), {row['wall_seconds']:.0f} s wall at load "
          f"{row['load_average'][0]:.1f}, {row['faces']:,} faces, mesh {row['mesh_sha256']}", flush=True)
    for label, s in sorted(row["stage_cpu_seconds"].items(), key=lambda kv: -kv[1]):
        print(f"  {label:28s} {s:8.1f} CPU-s  {s / row['cpu_seconds']:6.1%}", flush=True)


def main(argv: list[str] | None = None) -> dict:
    os.environ.setdefault("LP_NUM_THREADS", "1")  # llvmpipe's threads (before moderngl loads)
    import cv2
    import torch

    from omnirecon.data.io import write_json
    from omnirecon.engine.checkpoint import fingerprint, load_checkpoint
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=sorted(SCENES))
    p.add_argument("--views", type=int, default=0, help="mesh this many of the views, evenly spaced (0: all)")
    p.add_argument("--meshes", type=Path, default=None, help="also write each mesh (PLY) into this folder")
    p.add_argument("--label", default="", help="a name for the code measured (e.g. 'before'): rows of other labels stay")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    ckpt = ROOT / "checkpoints" / "omnirecon-tiny"
    model = load_checkpoint(ckpt)[0]
    if a.meshes is not None:
        a.meshes.mkdir(parents=True, exist_ok=True)
    out_file = a.out / "mesh_speed.json"
    old = json.loads(out_file.read_text()) if out_file.is_file() else {}
    result = {"provenance": provenance(seed=0), "checkpoint": {**fingerprint(ckpt), "path": "checkpoints/omnirecon-tiny"},
              "rows": old.get("rows", [])}
    for name in a.scenes:
        row = {"label": a.label, **run_row(name, a.views or None, model, a.meshes)}
        same = (name, row["views"], a.label)
        result["rows"] = [r for r in result["rows"] if (r["scene"], r["views"], r.get("label", "")) != same] + [row]
        print_row(row)
        write_json(out_file, result)
    return result
