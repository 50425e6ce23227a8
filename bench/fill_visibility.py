"""What the mesh path's fill and occlusion test buy before tuning: held-out PSNR and coverage.

    python -m bench fill_visibility --scene fern=../shared/data/llff/fern --mesh fern=MESH.ply

Per scene and mesh (the project's own ``omnirecon mesh --views all`` meshes): the protocol's held-out
views (at most 4, evenly spaced) rendered by :class:`~omnirecon.mesh.ibr.MeshRenderer` from the default
3 sources at the protocol's 128-px long side, with ``fill`` far / background and ``visibility`` off /
on; PSNR over the whole image (and the object masks where the scene has them) and coverage (held-out
pixels on the mesh). Merges into ``bench/results/fill_visibility.json``.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
import torch

from omnirecon.data.io import write_json

ROOT = Path(__file__).resolve().parents[1]


def run_scene(path: Path, mesh_file: Path) -> dict:
    from omnirecon import metrics
    from omnirecon.data import detect_format
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.engine.protocols import protocol_for, targets_and_pool
    from omnirecon.engine.views import default_views
    from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions
    from omnirecon.rays import Sources
    from omnirecon.workflows.mesh import scene_frame_mesh

    scene, mesh = scene_frame_mesh(path, mesh_file, 128)
    targets, _ = targets_and_pool(protocol_for(path, detect_format(path)), scene)
    targets = [targets[i] for i in np.unique(np.linspace(0, len(targets) - 1, 4).round().astype(int))]
    views = default_views(scene, 3)
    model, _ = load_checkpoint(ROOT / "checkpoints" / "omnirecon-tiny")
    bg = tuple(scene.background) if scene.background is not None else (1.0, 1.0, 1.0)
    rows = {}
    for fill in ("far", "background"):
        for vis in (False, True):
            opts = MeshRenderOptions(background=bg, visibility=vis, fill=fill, cull_back_faces=False)
            with MeshRenderer(model, mesh, Sources.from_scene(scene, views), opts) as r:
                outs = [r.render(scene.cameras[t]) for t in targets]
            rgb = [o["rgb"].float().clamp(0, 1) for o in outs]
            row = {"psnr": float(np.mean([metrics.psnr(x, scene.images[t].float()) for x, t in zip(rgb, targets)])),
                   "coverage": float(np.mean([o["mask"].float().mean() for o in outs]))}
            if scene.masks is not None:
                row["psnr_masked"] = float(np.mean([metrics.psnr(x, scene.images[t].float(), scene.masks[t])
                                                    for x, t in zip(rgb, targets)]))
            rows[f"fill={fill} visibility={vis}"] = row
            print(path.name, fill, vis, row, flush=True)
    return {"scene": str(path), "mesh": str(mesh_file), "faces": len(mesh.faces), "held_out": targets,
            "sources": views, "rows": rows, "load_average": os.getloadavg()[0]}


def main(argv: list[str] | None = None) -> dict:
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", action="append", required=True, help="NAME=PATH (repeatable)")
    p.add_argument("--mesh", action="append", required=True, help="NAME=MESH.ply (input frame)")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    meshes = dict(s.split("=", 1) for s in a.mesh)
    file = a.out / "fill_visibility.json"
    for name, path in (s.split("=", 1) for s in a.scene):
        result = json.loads(file.read_text()) if file.is_file() else {"scenes": {}}
        result["scenes"][name] = run_scene(Path(path), Path(meshes[name]))
        result["provenance"] = provenance(seed=0)
        write_json(file, result)
    return result

