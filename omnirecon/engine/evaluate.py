"""Evaluation (``omnirecon eval``): score a model on held-out views under one fixed protocol per dataset.

The protocols (which views are targets, which form the source pool, resolution, background,
masks, crops) live in :mod:`omnirecon.engine.protocols` and are documented in ``docs/evaluation.md``. For every
scene, every source-view count ``K`` (3 and 10 by default) and every target view, the model
encodes the ``K`` sources chosen by :func:`select_sources` (the K nearest pool views; DTU's
3-view setting uses the fixed views 23, 24, 33), renders the target in chunks, and the render
is scored against the ground truth with :mod:`omnirecon.metrics`.

Python use (benchmark scripts)::

    from omnirecon.engine.evaluate import evaluate
    from omnirecon.models.registry import build_model
    result = evaluate(build_model("floor"), ["synth:eval", "../shared/data/llff/fern"], num_views=(3, 10),
                      out=Path("outputs/eval/floor"))
    result["means"]["synth"]["3"]["psnr"]
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from omnirecon import metrics
from omnirecon.cameras import closest_point_to_axes
from omnirecon.engine import eval_report
from omnirecon.engine.protocols import targets_and_pool
from omnirecon.engine.scenes import EvalScene, prepare_scenes
from omnirecon.engine.views import select_sources, view_metric
from omnirecon.errors import InputError
from omnirecon.mesh import geometry as geo
from omnirecon.mesh.build import MeshOptions, mesh_from_model
from omnirecon.mesh.depth import depth_from_outputs
from omnirecon.mesh.files import write_mesh
from omnirecon.mesh.geometry import depth_errors
from omnirecon.models.guided import GuidedOptions, render_guided
from omnirecon.options import check_value
from omnirecon.preflight import check_planned
from omnirecon.progress import progress_bar
from omnirecon.provenance import provenance
from omnirecon.rays import Sources


def score(pred: Tensor, gt: Tensor, mask: Tensor | None = None, crop: float = 0.0) -> dict[str, float]:
    """All metrics of one render ``pred # [H, W, 3]`` against ``gt`` (after cropping ``crop`` of each border)."""
    if crop > 0:
        h, w = gt.shape[:2]
        dy, dx = round(h * crop), round(w * crop)
        pred, gt = pred[dy:h - dy, dx:w - dx], gt[dy:h - dy, dx:w - dx]
        mask = None if mask is None else mask[dy:h - dy, dx:w - dx]
    out = {"psnr": metrics.psnr(pred, gt), "ssim": metrics.ssim(pred, gt)}
    for key, fn in (("st_lpips_alex", metrics.st_lpips), ("lpips_alex", metrics.lpips)):
        value = fn(pred, gt)
        if value is not None:
            out[key] = value
    if mask is not None:
        out["psnr_masked"] = metrics.psnr(pred, gt, mask)
    return out


def evaluate(
    model,
    scenes,
    num_views=(3, 10),
    out: Path | None = None,
    *,
    model_info: dict | None = None,
    chunk: int = 4096,
    device: str = "cpu",
    max_targets: int | None = None,
    synth_count: int = 10,
    cache: Path = Path("outputs/cache"),
    save_images: bool = True,
    progress: bool = True,
    seed: int = 0,
    protocol_set: str = "full",
    geometry: bool = False,
    mesh_options: MeshOptions | None = None,
    mesh_pictures: bool = True,
    mesh_masks: bool = False,
    guided: GuidedOptions | None = None,
) -> dict:
    """Evaluate ``model`` on ``scenes`` for each source count in ``num_views``; returns the results.

    Args:
        model: A :class:`~omnirecon.models.base.GeneralizableModel` (put in eval mode, moved to ``device``).
        scenes: Scene folders (read at protocol resolution), ``"synth:eval[:rig]"`` specs,
            :class:`Scene` objects (used at their own resolution, normalised) or prepared
            :class:`EvalScene` objects (used as they are).
        num_views: Source-view counts ``K``; a scene whose pool is smaller than ``K`` skips that K.
        out: Folder for ``results.json``, ``results.md`` and per-target panels; ``None`` writes nothing.
        model_info: Name/preset/checkpoint recorded in the results.
        chunk: Rays per rendering chunk.
        max_targets: Override the protocols' target caps (the results say so: not protocol numbers).
        synth_count: Scenes in a ``synth:eval`` set.
        save_images: Write a ``GT | render | error`` panel per target.
        progress: Show a progress bar with ETA.
        guided: Surface-guided rendering of the targets (:mod:`omnirecon.models.guided`; None or off: the full
            path); results record the options.
        seed: Seeds torch before rendering (models are deterministic at test time; recorded).
        protocol_set: ``"full"`` (the published protocols) or ``"cpu"`` (64 px, fewer targets).
        geometry: Also mesh each (scene, K) with :func:`geometry_sources` as the sources
            (``omnirecon mesh``'s protocol) and score the mesh on the targets: Chamfer / F-score
            against a procedural scene's exact mesh, silhouette IoU against the targets' masks.
            Per-target depth errors are reported whenever the model renders depth and the scene
            has ground-truth depth, with or without this flag.
        mesh_options: The mesh pipeline's settings for ``geometry`` (default :class:`MeshOptions` with
            ``chunk``: the model's depth). With a depth source that needs no model (``stereo``, ``oracle``)
            ``model`` may be ``None``: then nothing is rendered and only the meshes are scored.
        mesh_pictures: With ``geometry``, also write each mesh's picture (``mesh.png``).
        mesh_masks: Mesh with the scenes' object masks (carve, clean, complete inside them) and score objects
            only (Chamfer against the exact mesh's objects); ``False``: the whole scene (``omnirecon mesh``'s
            default).

    Returns:
        ``{"provenance", "model", "protocols", "num_views", "scenes": [...], "means": {protocol: {K: {...}}},
        "unavailable": {metric: reason}, "seconds_per_view"}`` (see ``docs/evaluation.md``).
    """

    ks = [int(k) for k in num_views]
    if not ks:
        raise InputError("--num-views needs at least one count", None, "use e.g. 3 10")
    for name, value in (("num_views", tuple(ks)), ("chunk", chunk), ("max_targets", max_targets)):
        check_value(name, value)  # the rules: omnirecon/options.py (None: unset)
    options = mesh_options or MeshOptions(depth="model", chunk=chunk)  # the model's geometry
    if model is None and not (geometry and options.depth in ("stereo", "oracle")):
        raise InputError("evaluating without a model needs geometry with a depth source that needs none", None,
                         "pass a model, or geometry=True with MeshOptions(depth='stereo')")
    torch.manual_seed(seed)
    if model is not None:
        model = model.to(device).eval()
    with progress_bar(disable=not progress, transient=False) as bar:
        prepared = [s for s in scenes if isinstance(s, EvalScene)]
        prepared += prepare_scenes([s for s in scenes if not isinstance(s, EvalScene)], synth_count, cache, bar,
                                   protocol_set)
        jobs, results = _plan(prepared, ks, max_targets)
        check_planned(jobs, results, ks)  # a K that runs nowhere: refused, not empty tables
        total = sum(len(job["targets"]) for job in jobs)
        task = bar.add_task("eval", total=total)
        for job in jobs:
            if model is not None:
                _run_job(model, job, chunk, device, out if save_images else None, bar, task, guided or GuidedOptions())
            else:
                job["views"] = []
                bar.advance(task, len(job["targets"]))
            if geometry:
                _mesh_job(model, job, options, device, out, mesh_pictures, mesh_masks)
    result = eval_report.collect(results, jobs, ks, {
        "provenance": provenance(seed=seed, chunk=chunk, eval_device=device),
        "model": model_info or {"name": type(model).__name__ if model is not None else options.depth},
        "protocol_set": protocol_set,
        "geometry": geometry,
        **({"guided": asdict(guided.resolved(model))} if guided is not None and guided.on else {}),
        **({"mesh_options": asdict(options), "mesh_masks": mesh_masks} if geometry else {}),
        "protocols": {s.protocol.name: asdict(s.protocol) for s in prepared},
        "non_protocol": {} if max_targets is None else {"max_targets": max_targets},
        "unavailable": {k: r for k, r in (("st_lpips_alex", metrics.unavailable("st_lpips")),
                                          ("lpips_alex", metrics.unavailable("lpips"))) if r},
    })
    if out is not None:
        eval_report.write(result, Path(out))
    return result


def _plan(scenes: list[EvalScene], ks: list[int], max_targets: int | None) -> tuple[list[dict], list[dict]]:
    """One job per (scene, K) that can run, and one result record per scene (skips noted there)."""
    jobs, records = [], []
    for es in scenes:
        targets, pool = targets_and_pool(es.protocol, es.scene, max_targets)
        rec = {"name": es.name, "path": None if es.path is None else str(es.path), "protocol": es.protocol.name,
               "rig": es.scene.rig, "resolution": [es.scene.width, es.scene.height], "targets": targets,
               "pool": pool, "settings": {}, "skipped": {}}
        records.append(rec)
        fixed = dict(es.protocol.fixed_sources)
        center = closest_point_to_axes(es.scene.cameras) if view_metric(es.scene) == "angle" else None
        for k in ks:
            if k not in fixed and len(pool) < k:
                rec["skipped"][str(k)] = f"the source pool has {len(pool)} views, fewer than {k}"
                continue
            if min(es.scene.width, es.scene.height) < metrics.SSIM_WINDOW:  # scored with SSIM's window: no smaller
                raise InputError(f"images are {es.scene.width}x{es.scene.height} px, smaller than SSIM's "
                                 f"{metrics.SSIM_WINDOW} px window", es.path, "evaluate a scene with larger images")
            sources = [list(fixed[k]) if k in fixed else select_sources(es.scene, es.scene.cameras[t], pool, k, center)
                       for t in targets]
            jobs.append({"scene": es, "k": k, "targets": targets, "sources": sources, "record": rec})
    return jobs, records


def _run_job(model, job: dict, chunk: int, device: str, out: Path | None, bar, task, guided: GuidedOptions) -> None:
    """Render and score every target of one (scene, K) job; fills ``job["views"]``."""

    es: EvalScene = job["scene"]
    scene, k = es.scene, job["k"]
    bar.update(task, description=f"{es.name} K={k}")
    features, key = None, None
    views = []
    for t, src in zip(job["targets"], job["sources"]):
        start, cpu = time.perf_counter(), time.process_time()
        if tuple(src) != key:  # DTU's fixed sources are encoded once
            features, key = model.encode(Sources.from_scene(scene, src).to(device)), tuple(src)
        camera = scene.cameras[t].to(device=device, dtype=scene.images.dtype)
        rendered = render_guided(model, features, camera, guided, chunk)
        seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
        gt = scene.images[t]
        mask = scene.masks[t] if es.protocol.masked and scene.masks is not None else None
        row = {"index": t, "name": scene.names[t], "sources": src, "seconds": seconds, "cpu_seconds": cpu}
        if "depth" in rendered and scene.depths is not None:
            depth, _ = depth_from_outputs(rendered)
            err = depth_errors(depth, scene.depths[t], None if mask is None else mask.bool())
            row.update({"depth_abs_rel": err["abs_rel"], "depth_delta1": err["delta1"]})
        preds = {"": rendered["rgb"]} | ({"_aux": rendered["rgb_aux"]} if "rgb_aux" in rendered else {})
        for suffix, pred in preds.items():
            pred = pred.detach().float().cpu().clamp(0, 1)
            row.update({f"{m}{suffix}": v for m, v in score(pred, gt, mask, es.protocol.crop).items()})
            if out is not None:
                name = f"{t:03d}_{Path(scene.names[t]).stem}{suffix}.png"
                eval_report.write_panel(Path(out) / es.name / f"k{k}" / name, gt, pred)
        views.append(row)
        bar.advance(task)
    job["views"] = views


def geometry_sources(es: EvalScene, k: int) -> list[int]:
    """Source views of the mesh scored for (scene, ``k``): the protocol's fixed sources when it has
    them (DTU 23, 24, 33), else ``omnirecon mesh``'s default (``k`` evenly spaced pool views)."""
    fixed = dict(es.protocol.fixed_sources)
    if k in fixed:
        return list(fixed[k])
    _, pool = targets_and_pool(es.protocol, es.scene)
    pick = np.unique(np.linspace(0, len(pool) - 1, k).round().astype(int))
    return [pool[i] for i in pick]


def _mesh_job(model, job: dict, options: MeshOptions, device: str, out: Path | None, picture: bool = True,
              masks: bool = False) -> None:
    """Mesh one (scene, K) job with :func:`geometry_sources` and score it on the job's targets;
    fills ``job["geometry"]`` (and writes ``<out>/<scene>/k<K>/mesh.ply`` and, with ``picture``, ``mesh.png``,
    the mesh seen from the first source view at a 512-px long side). ``resolved``: the
    surface, depth source and depth pass the run's ``auto`` options became for this scene. ``cpu_seconds`` splits the
    process CPU time by part: ``depth`` (the depth source), ``mesh`` (fusion to completion), ``score``, ``write``."""

    es: EvalScene = job["scene"]
    views = geometry_sources(es, job["k"])
    start = time.perf_counter()
    made = mesh_from_model(model, es.scene, views, options, device, use_masks=masks)
    seconds, cpu1 = time.perf_counter() - start, time.process_time()
    cpu = dict(made.info["cpu_seconds"])
    base = {"views": views, "seconds": seconds, "stage_seconds": made.info["seconds"],
            "depth_source": made.info["depth_source"].get("source"),
            "valid_depth_fraction": made.info["valid_depth_fraction"],
            "resolved": {k: made.info["options"][k] for k in ("surface", "depth", "depth_pass")}}  # "auto" as used
    if len(made.mesh.faces) == 0:
        job["geometry"] = {**base, "empty": True, "cpu_seconds": cpu}
        return
    scored = geo.score_mesh(made, es.scene, job["targets"])
    cpu2 = time.process_time()
    cpu["score"] = cpu2 - cpu1
    row = {**base, "faces": len(made.mesh.faces)}
    if "chamfer" in scored:
        c = scored["chamfer"]
        row.update({k: c[k] for k in ("chamfer", "accuracy", "completeness", "fscore", "precision", "recall",
                                      "accuracy_dropped", "completeness_dropped", "threshold")})
        row["chamfer_rel"] = scored["chamfer_rel"]
    if "mask_iou" in scored:
        row["mask_iou"] = scored["mask_iou"]["mean"]
    if "rendered_depth" in scored:
        row["fused_depth_abs_rel"] = scored["rendered_depth"]["abs_rel"]
    if out is not None:
        folder = Path(out) / es.name / f"k{job['k']}"

        write_mesh(made.mesh, [folder / "mesh.ply"], es.scene.to_input)
        if picture:
            cam = es.scene.cameras[views[0]]
            geo.save_picture(folder / "mesh.png", made.mesh, cam.rescaled(max(1.0, 512 / max(cam.width, cam.height))))
    cpu["write"] = time.process_time() - cpu2
    row["cpu_seconds"] = cpu
    job["geometry"] = row
