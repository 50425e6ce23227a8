"""Geometry error budget, stage by stage, on procedural scenes (issue 16).

    python -m bench geometry_budget                      # demo scene + 2 synth:eval scenes (~15 CPU-min)
    python -m bench geometry_budget --tiny               # one scene at 48 px, oracle and floor (tests)

For each scene (the demo's held-out scene, seed 900999, 24 views at 128 px, and the first
``--scenes`` of ``synth:eval``) and each depth source (``oracle``: the exact mesh's depth; ``stereo``: classical stereo;
``floor``; ``omnirecon-tiny``), at the 3 default source views and at every training view (``all``, each depth
map from its own 3 nearest views), the depth maps go through

* ``reference``: VolRecon's protocol as main had it (depth at shifted views, nearest-pixel TSDF at
  1/256 of the diagonal, weight 1, cleaned with the source masks), 3 views only, and
* ``fit``: the pipeline's default preset (no masks: the background is kept; completion on),

and the mesh after each stage (marching cubes, visibility, components, face budget) is scored:
Chamfer distance over the observed ground truth's extent and F-score (at 1 % of the bounds
diagonal) against the whole exact mesh (ground included), and the mesh path's whole-image
held-out PSNR (omnirecon-tiny's appearance branch, the 3 default sources, the test split, no
visibility test: ``omnirecon finetune``'s step-0 score). The exact mesh's own row is the target;
the depth row gives each source's abs rel / delta<1.25 against the exact mesh. Seconds per stage
are 1-thread CPU seconds.

Writes ``bench/results/geometry_budget.json`` and the pictures of the mesh path to
``bench/results/figures/``. Depth maps are cached under ``outputs/cache/geometry_budget``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from omnirecon.data.io import write_json

ROOT = Path(__file__).resolve().parents[1]
DEMO_SEED = 900_999


def mesh_path_psnr(model, scene, sources, targets, mesh, picture: Path | None = None) -> float:
    """Whole-image held-out PSNR of ``mesh`` through the mesh path (no visibility test)."""
    from omnirecon import metrics
    from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions
    from omnirecon.models.base import Sources

    if len(mesh.faces) == 0:
        return float("nan")
    bg = tuple(scene.background) if scene.background is not None else (1.0, 1.0, 1.0)
    opts = MeshRenderOptions(background=bg, cull_back_faces=False)
    with MeshRenderer(model, mesh, Sources.from_scene(scene, sources), opts) as r:
        renders = [r.render(scene.cameras[t], extras=False)["rgb"].float().clamp(0, 1) for t in targets]
    if picture is not None:
        from omnirecon.data.io import write_image

        top = torch.cat(renders, 1)
        bottom = torch.cat([scene.images[t].float() for t in targets], 1)
        write_image(picture, (torch.cat([top, bottom], 0).numpy() * 255 + 0.5).astype(np.uint8))
    return float(np.mean([metrics.psnr(x, scene.images[t].float()) for x, t in zip(renders, targets)]))


def score(mesh, scene, targets, model, sources, picture=None) -> dict:
    from omnirecon.mesh import geometry

    e = geometry.evaluate_mesh(mesh, scene, targets)
    c = e["chamfer"]
    return {"faces": len(mesh.faces), "chamfer_rel": c["chamfer"] / c["gt_extent"], "fscore": c["fscore"],
            "precision": c["precision"], "recall": c["recall"],
            "held_out_depth_abs_rel": e.get("depth", {}).get("abs_rel"),
            "held_out_coverage": e.get("depth", {}).get("coverage"),
            "psnr": mesh_path_psnr(model, scene, sources, targets, mesh, picture)}


def depth_maps(source: str, scene, views, k: int, shifts, cache: Path, models: dict):
    """:class:`~omnirecon.mesh.depth.DepthMaps` of ``source`` at ``views`` (shifted by ``shifts``), cached on disk."""
    from omnirecon.mesh.build import MeshOptions, depth_maps

    key = cache / f"{source}_{'-'.join(map(str, views))}_k{k}_s{'-'.join(f'{s:.4f}' for s in shifts)}.pt"
    if source not in ("oracle", "stereo") and key.is_file():
        return torch.load(key, weights_only=False)
    depth = source if source in ("oracle", "stereo") else "model"
    maps = depth_maps(MeshOptions(depth=depth, shifts=tuple(shifts), neighbours=k), scene, views, models.get(source))
    if depth == "model":
        cache.mkdir(parents=True, exist_ok=True)
        torch.save(maps, key)
    return maps


def run_case(scene, name, source, setting, views, pipeline, models, mesh_model, sources, targets, cache, figures):
    from omnirecon.mesh import geometry
    from omnirecon.mesh.build import DTU_SHIFT, MeshOptions, mesh_from_depths

    shifts = (DTU_SHIFT,) if pipeline == "reference" else (0.0,)
    maps = depth_maps(source, scene, views, 3, shifts, cache, models)
    row = {"scene": name, "source": source, "views": setting, "num_maps": len(maps.cameras),
           "pipeline": pipeline, "render_seconds": maps.info["seconds"],
           "model_calls": maps.info.get("model_calls", {"encode": 0, "render_view": 0})}
    row["depth"] = geometry.rendered_depth_errors(scene, maps.cameras, maps.depth).get("rendered_depth")
    stages: dict = {}
    if pipeline == "reference":  # VolRecon's protocol: a preset of the one pipeline, cleaned with the masks
        made = mesh_from_depths(maps, scene, views, MeshOptions.preset("reference"), scene.masks, stages=stages)
    else:
        made = mesh_from_depths(maps, scene, views, MeshOptions(max_faces=100_000), stages=stages)
        row.update({k: made.info[k] for k in ("voxel", "trunc", "depth_disagreement", "mean_weight")})
    row["seconds"] = made.info["seconds"]
    row["stages"] = {}
    last = list(stages)[-1]
    for stage, mesh in stages.items():
        pic = figures / f"budget_{name}_{source}_{setting}_{pipeline}.png" if stage == last else None
        row["stages"][stage] = score(mesh, scene, targets, mesh_model, sources, pic)
    return row


def main(argv: list[str] | None = None) -> dict:
    from omnirecon.data import detect_format
    from omnirecon.data.synth.generate import SynthOptions, generate_scene
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.engine.protocols import protocol_for, targets_and_pool
    from omnirecon.engine.scenes import load_at_resolution, synth_eval_paths
    from omnirecon.engine.views import default_views
    from omnirecon.models.registry import build_model
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", type=int, default=2, help="synth:eval scenes besides the demo scene")
    p.add_argument("--sources", nargs="+", default=["oracle", "stereo", "floor", "omnirecon-tiny"])
    p.add_argument("--all-views-for", nargs="+", default=["oracle", "stereo", "floor", "omnirecon-tiny@demo"],
                   help="depth sources meshed from every training view (NAME@demo: the demo scene only)")
    p.add_argument("--tiny", action="store_true", help="the demo scene at 48 px, oracle and floor (tests)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    ckpt = ROOT / "checkpoints" / "omnirecon-tiny"
    mesh_model, _ = load_checkpoint(ckpt)
    models = {"floor": build_model("floor")}
    if "omnirecon-tiny" in a.sources and not a.tiny:
        models["omnirecon-tiny"] = mesh_model
    sources_wanted = [s for s in a.sources if (s == "oracle" or (s == "stereo" and not a.tiny)) or s in models]
    res = 48 if a.tiny else 128
    cache = ROOT / "outputs" / "cache" / "geometry_budget"
    scenes = [("demo", generate_scene(cache / f"demo_{res}", DEMO_SEED,
                                      SynthOptions(rig="object", views=24, resolution=res)))]
    if not a.tiny:
        scenes += [(s.name, s) for s in synth_eval_paths("synth:eval", a.scenes, ROOT / "outputs" / "cache")]
    figures = a.out / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    rows, exact = [], {}
    for name, path in scenes:
        fmt = detect_format(path)
        proto = protocol_for(path, fmt)
        scene = load_at_resolution(path, res, proto.background, fmt)
        targets, pool = targets_and_pool(proto, scene)
        k3 = default_views(scene, 3)
        from omnirecon.mesh import geometry

        exact[name] = score(geometry.ground_truth_mesh(scene), scene, targets, mesh_model, k3,
                            figures / f"budget_{name}_exact.png")
        exact[name].update({"sources": k3, "targets": targets, "train_views": len(pool)})
        print(name, "exact", f"{exact[name]['psnr']:.2f} dB", flush=True)
        cache_s = cache / f"{name}_{res}"
        for source in sources_wanted:
            settings = [("k3", k3, "reference"), ("k3", k3, "fit")]
            if source in a.all_views_for or f"{source}@{name}" in a.all_views_for:
                settings.append(("all", list(pool), "fit"))
            for setting, views, pipeline in settings:
                row = run_case(scene, name, source, setting, views, pipeline, models, mesh_model, k3, targets,
                               cache_s, figures)
                rows.append(row)
                last = list(row["stages"].values())[-1]
                print(f"{name} {source} {setting} {pipeline}: Chamfer {100 * last['chamfer_rel']:.2f} % "
                      f"F {last['fscore']:.3f} PSNR {last['psnr']:.2f} dB", flush=True)
    from omnirecon.engine.checkpoint import fingerprint

    result = {"provenance": provenance(seed=0), "mesh_path_checkpoint": {**fingerprint(ckpt),
                                                                         "path": "checkpoints/omnirecon-tiny"},
              "resolution": res, "tiny": a.tiny, "exact": exact, "rows": rows, "oracle_tolerance_db": 0.5}
    write_json(a.out / "geometry_budget.json", result)
    return result

