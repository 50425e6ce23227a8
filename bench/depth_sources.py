"""Depth source x scene: what each depth source's mesh gives through the mesh path (issue 24).

    python -m bench depth_sources                      # every row below (tens of CPU-minutes)
    python -m bench depth_sources --rows fern:stereo+fill dtu_scan24:stereo+fill
    python -m bench depth_sources --tiny               # the demo scene at 48 px, oracle and stereo (tests)

Per scene (fern at its photos' resolution, 336x252; dtu_scan24/37 at 400x300 with their object masks; NeRF-synthetic's
lego at 400x400 on white (100 training views meshed, its first 4 test views scored); fox, a real handheld capture (no
masks or known background) at 225x400, 58 views meshed, 4 of 9 held out scored; the demo's held-out procedural scene,
seed 900999, and the ``synth:eval`` seeds 900998, 900997 and 900000 (``synth_<seed>``), 24 views at 128 px) and source:

* ``learned``: omnirecon-tiny's coarse-pass depth at 128 px, each view from its 3 nearest views;
* ``floor``: the plane-sweep floor's depth, the same way;
* ``stereo``: classical stereo (``omnirecon/mesh/stereo.py``) at the photos' resolution, no completion;
* ``stereo+fill``: the same with completion (``omnirecon/mesh/complete.py``): every content pixel of
  every meshed view covered (fill from the view's depth, a backdrop on forward-facing scenes);
* ``stereo+model``: stereo at the photos' resolution where it matched, omnirecon-tiny's coarse-pass depth
  (rendered at 128 px, read at the photos' pixels) for the rest, with completion;
* ``stereo+model+poisson``: the same with screened Poisson over the fused surface, trimmed to the masks
  (object captures; ``omnirecon/mesh/poisson.py``);
* ``oracle``: the exact depth (procedural scenes), with completion;
* ``<source>, coherent``: the same depth through the coherent surface (``MeshOptions.surface="coherent"``,
  ``omnirecon/mesh/surface.py``: confirmed points, screened Poisson, a background layer, no fills);
* ``<source>, sky kept`` (procedural scenes): the same without dropping depth where the photo shows the
  scene's known background colour (``MeshOptions.drop_background=False``): what that step is worth;
* ``<source>, K sources`` / ``<source>, exposure``: the same mesh scored with ``finetune --num-views K`` (the
  mesh path blends K source views instead of 3) / tuned with ``--tune encoder appearance exposure``
  (variants combine: ``stereo+fill, 8 sources, exposure``);
* ``<source>, nearest K``: scored with ``finetune --nearest K``: every training view but the validation
  views is a source, and each pixel blends the K sources nearest its view (DTU: about 10 degrees away, against
  11-57 degrees for the fixed 23 24 33);
* ``<source>, all views`` (DTU): the mesh from every training view (41) instead of 14 of them.
* ``<source>, angle blend``: scored with ``finetune --blend angle`` (each point's nearest sources by viewing
  angle, weighted by angle alone: ``omnirecon.mesh.kernel.angle_weights``; nothing is tuned).
* ``<source>, nearest fill``: scored with ``finetune --fill nearest`` (pixels the mesh misses take the z-depth of
  the nearest pixel it covers in the same view, instead of the far layer).
* ``<source>, angle auto``: with the angle blend, ``finetune --angle-sources 3 4 6 8`` (the count that scores best
  on the validation views).
* ``<source>, consensus S``: with the angle blend, ``finetune --consensus S`` (sources whose colour disagrees with
  the blend down-weighted: ``omnirecon.mesh.kernel.consensus_weights``).
* ``<source>, no source masks``: with the angle blend, ``finetune --no-source-masks`` (each source weighted by angle
  alone, not also by :func:`omnirecon.mesh.kernel.mask_falloff` at its pixel; the default before session 16).
* ``<source>, no cracks``: scored with ``finetune --cracks 0`` (the missed pixels the mesh encloses keep the fill or
  the background colour instead of the nearest covered pixel's depth; the default before session 18).
* ``<source>, match N``: stereo matched on rectified pairs resampled to a long side of N px (at most twice the
  photos'; ``StereoOptions.match_side``) instead of the default.
* ``<source>, N held-out``: scored on N of the protocol's held-out views (``finetune --max-held-out N``, evenly
  spaced) instead of 4: DTU's protocol holds out 8 (0 6 13 19 28 35 42 48), the 4-view rows score 0 13 35 48.
* ``<source>, no soften``: scored with ``finetune --soften 0`` (no blur at the mesh's depth edges:
  :func:`omnirecon.render.edges.soften_edges`; the default before session 17).
* ``exact mesh, <variants>`` (procedural, with ``--rows``): the exact mesh scored with those variants (``demo:exact
  mesh, nearest 6``), the like-for-like target of rows scored that way.

Rows of one run that differ only in scoring share one mesh (made once; each row records ``mesh_file``). Without
``, angle blend`` / ``, nearest fill`` a row is scored with the network's blend and the far layer (the scene's
background colour where known), whatever ``finetune``'s per-scene defaults. DTU rows also record the training views'
mask coverage (``training_coverage``: what cleaning must never delete). Each mesh is made from the scene's training views minus the protocol's held-out views (DTU: 14 of
them, evenly spaced) by the one pipeline (``omnirecon/mesh/build.py``) and scored like
``omnirecon finetune --mesh M --clock cpu --threads 1``: held-out PSNR of the mesh path before and after
``--seconds`` of tuning (whole image; over the object masks on DTU; over the covered pixels), coverage
(held-out pixels on the mesh, inside the masks on DTU), silhouette IoU (DTU), Chamfer and F-score
against the exact mesh (procedural), and the CPU seconds of images -> mesh (this process, 1 thread).
A picture per row (ground truth | before | after on the first held-out view) goes to
``bench/results/figures/depth_sources_<scene>_<source>.png``. Rows are written as they finish.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from bench.depth_rows import MESH_VARIANTS, WORK, mesh_settings
from omnirecon.data.io import write_json

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
DEMO_SEED = 900_999
PROCEDURAL = {"demo": DEMO_SEED, "synth_900998": 900_998, "synth_900997": 900_997, "synth_900000": 900_000}
"""Procedural scenes by seed (object rig, 24 views at 128 px): the demo's and three of the held-out ``synth:eval`` seeds
(``omnirecon.splits.EVAL_SEEDS``; 900000 is the set's first scene)."""
SCENES = {"fern": "llff/fern", "dtu_scan24": "neus_dtu/dtu_scan24", "dtu_scan37": "neus_dtu/dtu_scan37",
          "lego": "blender/lego", "fox": "instant_ngp/fox", **{name: None for name in PROCEDURAL}}
SOURCES = ("learned", "floor", "stereo", "stereo+fill", "stereo+model", "stereo+model+poisson", "oracle")
TUNED = ("stereo+fill", "stereo+model", "stereo+model+poisson")
"""Sources tuned for ``--seconds`` (the others are scored before tuning only, to keep the run short)."""
DTU_VIEWS = 14


def load(name: str, tiny: bool):
    from omnirecon.data import detect_format
    from omnirecon.engine.protocols import protocol_for
    from omnirecon.engine.scenes import load_at_resolution

    if name in PROCEDURAL:
        from omnirecon.data.synth.generate import SynthOptions, generate_scene

        res = 48 if tiny else 128
        path = generate_scene(ROOT / "outputs" / "cache" / "depth_sources" / f"{name}_{res}", PROCEDURAL[name],
                              SynthOptions(rig="object", views=24, resolution=res))
    else:
        path = SHARED / SCENES[name]
        res = 512  # the photos' own resolution (fern 336x252, DTU 400x300)
    fmt = detect_format(path)
    proto = protocol_for(Path(path), fmt)
    return Path(path), load_at_resolution(path, res, proto.background, fmt), proto, res


def held_out(scene, proto, cap: int = 4, every_view: bool = False):
    """The targets ``omnirecon finetune`` scores (at most ``cap``, evenly spaced) and the meshing views (DTU: 14
    evenly spaced training views, or with ``every_view`` all of them)."""
    from omnirecon.engine.protocols import targets_and_pool

    targets, pool = targets_and_pool(proto, scene)
    all_targets = set(targets)
    if len(targets) > cap:
        targets = [targets[i] for i in np.unique(np.linspace(0, len(targets) - 1, cap).round().astype(int))]
    views = [v for v in pool if v not in all_targets]
    if proto.name == "dtu" and len(views) > DTU_VIEWS and not every_view:
        views = [views[i] for i in np.unique(np.linspace(0, len(views) - 1, DTU_VIEWS).round().astype(int))]
    return targets, views


def make_mesh(source: str, path: Path, scene, proto, views, masks: bool, models: dict):
    """The pipeline's result for ``source``, the similarity to the input frame, and the CPU seconds of
    this process."""
    from omnirecon.engine.scenes import load_at_resolution
    from omnirecon.mesh.build import MeshOptions, mesh_from_model

    source, _, variant = source.partition(", ")
    mesh_kw = mesh_settings(variant)
    t = time.process_time()
    if source in ("learned", "floor"):  # depth at 128 px (as `omnirecon reconstruct --mesh-resolution 128`)
        low = load_at_resolution(path, 128, proto.background) if max(scene.width, scene.height) > 128 else scene
        opts = MeshOptions(depth="model", depth_pass="coarse", **mesh_kw)
        made = mesh_from_model(models[source], low, views, opts, use_masks=masks)
        return made, low.to_input, time.process_time() - t
    if source.startswith("stereo+model"):  # stereo at the photos' resolution, the model's coarse depth (128 px)
        opts = MeshOptions(depth="stereo+model", depth_pass="coarse",  # for the rest
                           **{"surface": "poisson" if source.endswith("+poisson") else "fusion", **mesh_kw})
        made = mesh_from_model(models["learned"], scene, views, opts, use_masks=masks)
    else:
        opts = MeshOptions(depth="oracle" if source == "oracle" else "stereo", complete=source != "stereo", **mesh_kw)
        made = mesh_from_model(None, scene, views, opts, use_masks=masks)
    return made, scene.to_input, time.process_time() - t


def coverage_and_iou(mesh, scene, targets, masks: bool) -> dict:
    """Held-out pixels on the mesh (inside the object masks with ``masks``) and the silhouette IoU (with
    ``masks``: object captures; a procedural scene's masks hold the objects, not its ground)."""
    from omnirecon.mesh import geometry
    from omnirecon.mesh.complete import DepthRenderer

    r = DepthRenderer(mesh)
    cov, iou = [], []
    for t in targets:
        hit = r(scene.cameras[t]) > 0
        if masks:
            m = scene.masks[t].numpy().astype(bool)
            cov.append(float((hit & m).sum() / max(1, m.sum())))
            iou.append(geometry.mask_iou(hit, m))
        else:
            cov.append(float(hit.mean()))
    r.close()
    out = {"coverage": float(np.mean(cov))}
    if iou:
        out["silhouette_iou"] = float(np.mean(iou))
    return out


def training_coverage(mesh, scene, views) -> dict:
    """Object captures with masks: the fraction of each meshed (training) view's mask pixels the mesh covers (what
    cleaning must never delete): mean, min and the three lowest views."""
    from omnirecon.mesh.complete import DepthRenderer

    r = DepthRenderer(mesh)
    cov = {}
    for v in views:
        m = scene.masks[v].numpy().astype(bool)
        cov[int(v)] = float(((r(scene.cameras[v]) > 0) & m).sum() / max(1, m.sum()))
    r.close()
    worst = sorted(cov.items(), key=lambda kv: kv[1])[:3]
    return {"mean": float(np.mean(list(cov.values()))), "min": worst[0][1], "lowest": [list(w) for w in worst]}


def picture(src: Path, dst: Path, max_width: int = 480) -> str:
    """``src`` at most ``max_width`` wide, 256 colours (one row per held-out view: keep the PNG small)."""
    from PIL import Image

    img = Image.open(src).convert("RGB")
    if img.width > max_width:
        img = img.resize((max_width, round(img.height * max_width / img.width)), Image.LANCZOS)
    dst.parent.mkdir(parents=True, exist_ok=True)
    img.quantize(256).save(dst, optimize=True)
    return str(dst.relative_to(dst.parents[1]))


def scoring(source: str, scene=None) -> dict:
    """``FinetuneConfig`` settings of a row's variants (``, K sources``, ``, exposure``; module docstring). Rows
    without ``, nearest K`` keep the 3 fixed sources they were measured with (``--nearest 0``); without ``, angle
    blend`` / ``, nearest fill`` the network's blend and the far layer (the scene's background colour where it is
    known), whatever finetune's per-scene defaults (``omnirecon.mesh.ibr.scene_blend``); the angle blend's sources
    per point are --nearest's count unless ``, angle auto``."""
    out = {"nearest": 0, "blend": "network", "angle_sources": (), "source_masks": True,
           "fill": "background" if scene is not None and scene.background is not None else "far"}
    for part in source.split(", ")[1:]:
        if part.endswith(" sources"):
            out["num_views"] = int(part.split()[0])
        elif part == "nearest fill":
            out["fill"] = "nearest"
        elif part.startswith("nearest "):
            out["nearest"] = int(part.split()[1])
        elif part == "exposure":
            out["tune"] = ("encoder", "appearance", "exposure")
        elif part == "angle blend":
            out["blend"] = "angle"
        elif part == "angle auto":
            out["angle_sources"] = (3, 4, 6, 8)
        elif part.startswith("consensus "):
            out["consensus"] = float(part.split()[1])
        elif part == "no source masks":
            out["source_masks"] = False
        elif part == "no cracks":
            out["cracks"] = 0
        elif part == "no soften":
            out["soften"] = 0.0
        elif part.endswith(" held-out"):
            out["max_held_out"] = int(part.split()[0])
        elif part not in MESH_VARIANTS and not part.startswith("match "):
            raise ValueError(f"unknown variant {part!r} of {source!r}")
    return out


MESHES: dict = {}
"""Meshes made in this run, by scene and the variants that change the mesh (``all views``, ``sky kept``, ``match N``): rows that
differ only in scoring (``nearest K``, ``angle blend``, ``nearest fill``, ...) score the same mesh file."""


def run_row(name: str, source: str, seconds: float, models: dict, results: Path, tiny: bool) -> dict | None:
    from omnirecon.mesh import geometry
    from omnirecon.mesh.files import read_mesh, write_mesh
    from omnirecon.workflows.finetune import FinetuneConfig, run_finetune

    path, scene, proto, res = load(name, tiny)
    if source == "oracle" and scene.mesh_path is None:
        return None
    targets, views = held_out(scene, proto, every_view="all views" in source.split(", ")[1:])
    masks = scene.masks is not None and proto.name == "dtu"
    variants = source.split(", ")[1:]
    key = (name, source.partition(", ")[0], *(v in variants for v in MESH_VARIANTS),
           tuple(v for v in variants if v.startswith("match ")), tiny)
    slug = source.replace("+", "_").replace(", ", "_").replace(" ", "_")
    work = WORK / f"{name}_{slug}"
    if key not in MESHES:
        made, to_input, mesh_s = make_mesh(source, path, scene, proto, views, masks, models)
        (mesh_file,) = write_mesh(made.mesh, [work / "mesh.ply"], to_input)
        MESHES[key] = made, mesh_s, mesh_file
    made, mesh_s, mesh_file = MESHES[key]
    mesh = read_mesh(mesh_file, scene.to_input)  # as the scoring sees it
    tuned = source.partition(", ")[0] in TUNED
    tune = seconds if tuned else 1.0
    ft = run_finetune(FinetuneConfig(ckpt=ROOT / "checkpoints" / "omnirecon-tiny", scene=path, seconds=tune,
                                     eval_at=(0.0,), clock="cpu", threads=1, mesh=mesh_file, resolution=res,
                                     out=work / "finetune", **{"max_held_out": 4, **scoring(source, scene)}),
                      fill_from=(made.info.get("completion") or {}).get("surface_faces"))
    first, last = ft["curve"][0], ft["curve"][-1]
    row = {"scene": name, "source": source, "views": len(views), "held_out": ft["held_out"],
           "resolution": [scene.width, scene.height], "faces": len(made.mesh.faces), "mesh_cpu_seconds": mesh_s,
           "mesh_file": str(Path(mesh_file).resolve().relative_to(ROOT)),
           "seconds": made.info["seconds"], "completion": made.info.get("completion"),
           "tuned_seconds": tune if tuned else 0.0, "source_views": ft.get("sources"),
           "visibility": ft.get("visibility", False), "blend": ft.get("blend", "network"), "tuned": ft.get("tuned"), "lr": ft.get("lr"),
           "psnr": {"before": first["psnr"], "after": last["psnr"] if tuned else None},
           "psnr_covered": {"before": first.get("psnr_covered"), "after": last.get("psnr_covered") if tuned else None},
           "defects": ft.get("defects"), **coverage_and_iou(mesh, scene, ft["held_out"], masks)}
    if masks:
        row["training_coverage"] = training_coverage(mesh, scene, views)
    if masks and "psnr_masked" in first:
        row["psnr_masked"] = {"before": first["psnr_masked"], "after": last["psnr_masked"] if tuned else None}
    if scene.mesh_path is not None:
        c = geometry.evaluate_mesh(mesh, scene, ft["held_out"])["chamfer"]
        row.update({"chamfer_rel": c["chamfer"] / c["gt_extent"], "fscore": c["fscore"]})
    row["picture"] = picture(work / "finetune" / "before_after.png",
                             results / "figures" / f"depth_sources_{name}_{slug}.png")
    return row


def exact_row(name: str, tiny: bool, source: str = "exact mesh") -> dict | None:
    """The exact mesh through the same scoring (procedural scenes): the target of the oracle row; ``source`` may
    carry scoring variants (``exact mesh, nearest 6``: the target of the rows scored that way)."""
    from omnirecon.mesh.files import write_mesh
    from omnirecon.mesh.geometry import ground_truth_mesh
    from omnirecon.workflows.finetune import FinetuneConfig, run_finetune

    path, scene, proto, res = load(name, tiny)
    gt = ground_truth_mesh(scene)
    if gt is None:
        return None
    work = WORK / f"{name}_exact{source[len('exact mesh'):].replace(', ', '_').replace(' ', '_')}"
    (mesh_file,) = write_mesh(gt, [work / "mesh.ply"], scene.to_input)
    ft = run_finetune(FinetuneConfig(ckpt=ROOT / "checkpoints" / "omnirecon-tiny", scene=path, seconds=1.0,
                                     eval_at=(0.0,), clock="cpu", threads=1, mesh=mesh_file, resolution=res,
                                     out=work / "finetune", **{"max_held_out": 4, **scoring(source, scene)}))
    return {"scene": name, "source": source, "psnr": {"before": ft["curve"][0]["psnr"], "after": None},
            "psnr_covered": {"before": ft["curve"][0].get("psnr_covered"), "after": None},
            **coverage_and_iou(gt, scene, ft["held_out"], False)}


def timing_row(source: str, models: dict, photos: int = 20, threads: int = 1) -> dict:
    """``photos`` photos of fern (its 20, 336x252 after the reader's downscale to <= 512 px) -> mesh with
    ``source`` (``stereo`` or ``stereo+model``): CPU seconds of this process per stage and wall seconds, from
    reading the images to the completed mesh, at ``threads`` torch / OpenCV threads; the goal is <= 60 s on 2
    cores (wall at 2 threads on a quiet machine; CPU seconds at 1 thread is the load-proof bound)."""
    import cv2

    from omnirecon.engine.scenes import load_at_resolution
    from omnirecon.mesh.build import MeshOptions, mesh_from_model

    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    t0, w0 = time.process_time(), time.perf_counter()
    scene = load_at_resolution(SHARED / SCENES["fern"], 512, "white")
    load_s = time.process_time() - t0
    views = list(range(min(photos, len(scene))))
    opts = MeshOptions(depth=source, depth_pass="coarse")
    t = time.process_time()
    made = mesh_from_model(models["learned"] if source == "stereo+model" else None, scene, views, opts)
    mesh_s, wall = time.process_time() - t, time.perf_counter() - w0
    return {"scene": "fern", "source": source, "timing": True, "photos": len(views), "threads": threads,
            "resolution": [scene.width, scene.height], "cpu_seconds": {"load": load_s, "images_to_mesh": load_s + mesh_s},
            "wall_seconds": wall,
            "stage_wall_seconds": made.info["seconds"], "faces": len(made.mesh.faces),
            "load_average": list(os.getloadavg())}


def main(argv: list[str] | None = None) -> dict:
    from omnirecon.engine.checkpoint import fingerprint, load_checkpoint
    from omnirecon.models.registry import build_model
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", nargs="+", default=None, help="SCENE:SOURCE pairs (default: every scene x source)")
    p.add_argument("--seconds", type=float, default=60.0, help="CPU seconds of tuning for the tuned sources")
    p.add_argument("--tiny", action="store_true", help="the demo scene at 48 px, oracle and stereo (tests)")
    p.add_argument("--timing", nargs="*", default=None, metavar="SOURCE",
                   help="only time 20 fern photos -> mesh with these sources (stereo, stereo+model)")
    p.add_argument("--threads", type=int, default=1, help="torch / OpenCV threads of the --timing rows")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    if a.timing:
        rows = []
    elif a.tiny:
        rows = [("demo", "oracle"), ("demo", "stereo+fill")]
    elif a.rows:
        rows = [tuple(r.split(":", 1)) for r in a.rows]
    else:
        rows = [(s, src) for s in SCENES for src in SOURCES]
    models = {"floor": build_model("floor")}
    ckpt = ROOT / "checkpoints" / "omnirecon-tiny"
    if any(src == "learned" or src.startswith("stereo+model") for _, src in rows) or a.timing:
        models["learned"] = load_checkpoint(ckpt)[0]
    out_file = a.out / "depth_sources.json"
    old = json.loads(out_file.read_text()) if out_file.is_file() and not a.tiny else {}
    keep = [r for r in old.get("rows", []) if r.get("timing") or (r["scene"], r["source"]) not in set(rows)]
    result = {"provenance": provenance(seed=0), "checkpoint": {**fingerprint(ckpt), "path": "checkpoints/omnirecon-tiny"},
              "tuning_seconds": a.seconds, "tiny": a.tiny, "rows": keep}
    scenes_done = {r["scene"] for r in keep if r["source"] == "exact mesh"}
    for source in a.timing or []:
        result["rows"] = [r for r in result["rows"] if not (r.get("timing") and r["source"] == source
                                                            and r.get("threads", 1) == a.threads)]
        row = timing_row(source, models, threads=a.threads)
        result["rows"].append(row)
        print(f"timing fern x{row['photos']} {source} at {a.threads} thread(s): "
              f"{row['cpu_seconds']['images_to_mesh']:.1f} CPU-s, {row['wall_seconds']:.1f} s wall", flush=True)
        write_json(out_file, result)
    for name, source in rows:
        if name not in scenes_done and name in PROCEDURAL and (name, "exact mesh") not in rows:  # else it is a row
            ex = exact_row(name, a.tiny)
            scenes_done.add(name)
            if ex:
                result["rows"].append(ex)
        row = exact_row(name, a.tiny, source) if source.startswith("exact mesh") else \
            run_row(name, source, a.seconds, models, a.out, a.tiny)
        if row is None:
            continue
        result["rows"].append(row)
        meshed = f", mesh {row['mesh_cpu_seconds']:.0f} CPU-s" if "mesh_cpu_seconds" in row else ""  # not the exact mesh
        defects = f", defects {row['defects']['any']:.1%}" if row.get("defects") else ""  # unsupported faces' pixels
        print(f"{name} {source}: PSNR {row['psnr']['before']:.2f} -> {row['psnr']['after'] or float('nan'):.2f} dB, "
              f"coverage {row['coverage']:.3f}{defects}{meshed}", flush=True)
        write_json(out_file, result)
    write_json(out_file, result)
    return result

