"""Quality of Omni-Recon's mesh path: held-out PSNR before and after seconds of fine-tuning, and what
the per-source visibility test buys.

    python -m bench mesh_path                    # 3 held-out procedural scenes + dtu_scan24/37
    python -m bench mesh_path --tiny             # one small procedural scene, 2 s (tests)

Per scene: the mesh of ``checkpoints/omnirecon-tiny`` from 3 source views (``omnirecon mesh``'s
protocol; the mesh ``python -m bench geometry`` wrote is reused when present), then

* the mesh path's held-out PSNR without and with the visibility test (:class:`MeshRenderer`), on the
  protocol's targets (at most 4), images at the ``full`` protocol's 128-px long side; over the whole
  image and over the ground-truth object masks (the meshes are cleaned with the masks, so they hold
  the objects only: procedural ground and DTU's table are not in them);
* ``omnirecon finetune`` of the 2-D encoder and the appearance branch on the scene's training views,
  scored at 0, 10, 30 and 60 s (and 180, 300 s on the DTU scans) of optimisation. The clock is this
  process's CPU time (``--clock cpu``), so other jobs on the machine do not shrink the budget; the
  JSON records it.

Writes ``bench/results/mesh_path.json`` and the PSNR curves to ``bench/results/figures/``.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np
import torch

from omnirecon.data.io import write_json

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
DTU = ["neus_dtu/dtu_scan24", "neus_dtu/dtu_scan37"]
SHORT = (0.0, 10.0, 30.0, 60.0)
LONG = (0.0, 10.0, 30.0, 60.0, 180.0, 300.0)


def visibility_psnr(model, scene, views, targets, mesh) -> dict:
    """Mesh-path PSNR on ``targets`` without and with the visibility test (``*_masked``: object pixels)."""
    from omnirecon import metrics
    from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions
    from omnirecon.rays import Sources

    bg = tuple(scene.background) if scene.background is not None else (1.0, 1.0, 1.0)
    out = {}
    for vis in (False, True):
        opts = MeshRenderOptions(background=bg, visibility=vis, cull_back_faces=False)
        with MeshRenderer(model, mesh, Sources.from_scene(scene, views), opts) as r:
            outs = {t: r.render(scene.cameras[t]) for t in targets}
            renders = {t: o["rgb"].float().clamp(0, 1) for t, o in outs.items()}
            key = "with" if vis else "without"
            out["coverage"] = float(np.mean([o["mask"].float().mean() for o in outs.values()]))  # held-out pixels on the mesh
            out[key] = float(np.mean([metrics.psnr(renders[t], scene.images[t].float()) for t in targets]))
            if scene.masks is not None:
                out[key + "_masked"] = float(np.mean([metrics.psnr(renders[t], scene.images[t].float(), scene.masks[t])
                                                      for t in targets]))
    return out


def run_scene(path: Path, name: str, times, tiny: bool, results: Path, threads: int) -> dict:
    from omnirecon.data import detect_format
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.engine.protocols import protocol_for
    from omnirecon.engine.scenes import load_at_resolution
    from omnirecon.engine.views import default_views
    from omnirecon.workflows.finetune import FinetuneConfig, run_finetune

    ckpt = ROOT / "checkpoints" / "omnirecon-tiny"
    res = 48 if tiny else 128
    geo = ROOT / "outputs" / "bench" / "geometry" / "omnirecon-tiny"
    cached = next((p for p in (geo / "synth" / path.name / "k3" / "mesh.ply", geo / "dtu" / path.name / "k3" / "mesh.ply")
                   if p.is_file()), None) if not tiny else None
    out = ROOT / "outputs" / "bench" / "mesh_path" / name
    cfg = FinetuneConfig(ckpt=ckpt, scene=path, seconds=max(times), eval_at=tuple(times), clock="cpu",
                         mesh=cached, resolution=res, out=out, threads=threads, max_held_out=4, nearest=0)
    ft = run_finetune(cfg)
    # the visibility ablation on the same mesh and held-out views, before tuning
    model, _ = load_checkpoint(ckpt)
    fmt = detect_format(path)
    proto = protocol_for(path, fmt)
    scene = load_at_resolution(path, res, proto.background, fmt)
    if cached is not None:
        from omnirecon.mesh.files import read_mesh

        mesh = read_mesh(cached, scene.to_input)
    else:
        from omnirecon.mesh.build import MeshOptions, mesh_from_model

        mesh = mesh_from_model(model, scene, default_views(scene, 3), MeshOptions(depth="model")).mesh
    vis = visibility_psnr(model, scene, ft["sources"], ft["held_out"], mesh)
    figures = results / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    for f in ("curve.png", "before_after.png"):
        shutil.copy2(out / f, figures / f"mesh_path_{name}_{f}")
    curve = {str(int(c["seconds"])): c["psnr"] for c in ft["curve"]}
    curve_masked = {str(int(c["seconds"])): c["psnr_masked"] for c in ft["curve"] if "psnr_masked" in c}
    curve_covered = {str(int(c["seconds"])): c["psnr_covered"] for c in ft["curve"] if "psnr_covered" in c}
    return {"name": name, "sources": ft["sources"], "held_out": ft["held_out"], "faces": ft["faces"],
            "mesh": "geometry bench mesh" if cached else "extracted here", "curve": curve, "curve_masked": curve_masked,
            "curve_covered": curve_covered, "coverage": ft["coverage"],
            "steps": {str(int(c["seconds"])): c["steps"] for c in ft["curve"]}, "visibility": vis,
            "tuned_parameters": ft["tuned_parameters"], "clock": ft["clock"],
            "pictures": {"curve": f"figures/mesh_path_{name}_curve.png",
                         "before_after": f"figures/mesh_path_{name}_before_after.png"}}


def main(argv: list[str] | None = None) -> dict:
    from omnirecon.engine.scenes import synth_eval_paths
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--synth-scenes", type=int, default=3)
    p.add_argument("--tiny", action="store_true", help="one procedural scene at 48 px, 2 s (tests)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    if not (ROOT / "checkpoints" / "omnirecon-tiny" / "model.safetensors").is_file():
        raise SystemExit("`python -m bench mesh_path` needs checkpoints/omnirecon-tiny (`python -m bench train_tiny` ships it)")
    jobs = [(s, s.name, (0.0, 1.0, 2.0) if a.tiny else SHORT)
            for s in synth_eval_paths("synth:eval", 1 if a.tiny else a.synth_scenes, ROOT / "outputs" / "cache")]
    if not a.tiny:
        jobs += [(SHARED / d, Path(d).name, LONG) for d in DTU if (SHARED / d).is_dir()]
    rows = []
    for path, name, times in jobs:
        rows.append(run_scene(Path(path), name, times, a.tiny, a.out, a.threads))
        print(name, {k: round(v, 2) for k, v in rows[-1]["curve"].items()}, rows[-1]["visibility"])
    from omnirecon.engine.checkpoint import fingerprint, ignoring

    ckpt = ROOT / "checkpoints" / "omnirecon-tiny"
    result = {"provenance": provenance(seed=0), "checkpoint": {**fingerprint(ckpt), **ignoring(ckpt),
                                                                 "path": "checkpoints/omnirecon-tiny"},
              "rows": rows, "tiny": a.tiny,
              "resolution": 48 if a.tiny else 128, "goal_gain_db_60s": 3.0}
    write_json(a.out / "mesh_path.json", result)
    return result

