"""``omnirecon eval``: score a model on held-out views under one fixed protocol per dataset.

The protocols (which views are targets, which form the source pool, resolution, background,
masks, crops) live in :data:`PROTOCOLS` and are documented in ``docs/evaluation.md``. For every
scene, every source-view count ``K`` (3 and 10 by default) and every target view, the model
encodes the ``K`` sources chosen by :func:`select_sources` (the K nearest pool views; DTU's
3-view setting uses the fixed views 23, 24, 33), renders the target in chunks, and the render
is scored against the ground truth with :mod:`omnirecon.metrics`.

Python use (benchmark scripts)::

    from omnirecon.eval import evaluate
    from omnirecon.models.registry import build_model
    result = evaluate(build_model("floor"), ["synth:eval", "../shared/data/llff/fern"], num_views=(3, 10),
                      out=Path("outputs/eval/floor"))
    result["means"]["synth"]["3"]["psnr"]
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from omnirecon import metrics
from omnirecon.cameras import closest_point_to_axes, nearest_views
from omnirecon.data import ReadOptions, detect_format, load_scene
from omnirecon.data.io import read_json
from omnirecon.data.scene import Scene
from omnirecon.errors import InputError
from omnirecon.chunk import pick_chunk
from omnirecon.outputs import prepare_out
from omnirecon.preflight import check_planned
from omnirecon.geometry import depth_errors
from omnirecon.models.base import Sources
from omnirecon.render.mesh import depth_from_outputs
from omnirecon.splits import EVAL_SEEDS

SYNTH_PREFIX = "synth:eval"
"""Scene spec of the held-out procedural set (``synth:eval`` or ``synth:eval:<rig>``)."""


# ---------------------------------------------------------------------- protocols
@dataclass(frozen=True)
class Protocol:
    """How one dataset is evaluated. Every field is part of the published protocol."""

    name: str
    """Protocol key, used in result tables."""
    datasets: str
    """Which scenes it applies to."""
    rule: Literal["test_split", "every_8th", "dtu"]
    """Target/pool rule: the reader's test split vs train split; every 8th view vs the rest; DTU's
    targets = views other than the 3 fixed sources, pool = every non-target view."""
    max_targets: int | None = None
    """Cap on target views (picked by ``pick``), for CPU cost."""
    pick: Literal["first", "even"] = "first"
    """How the cap picks targets: the first ones, or evenly spaced over the candidates."""
    fixed_sources: tuple[tuple[int, tuple[int, ...]], ...] = ()
    """``(K, views)`` pairs: for these K every target uses exactly these source views."""
    long_side: int = 128
    """Images are area-downscaled so the long side is at most this many pixels (never upscaled)."""
    background: Literal["white", "black"] = "white"
    """Colour RGBA inputs are composited on (for sources and ground truth alike)."""
    masked: bool = False
    """Also report ``psnr_masked``: PSNR over the foreground-mask pixels of the ground truth."""
    crop: float = 0.0
    """Fraction of each border cropped before scoring (0 = the full image)."""


PROTOCOLS: dict[str, Protocol] = {
    "blender": Protocol("blender", "Blender / NeRF-synthetic (lego, chair)", "test_split", max_targets=8,
                        pick="first", masked=True),
    "dtu": Protocol("dtu", "DTU (NeuS or MVSNet layout; dtu_scan24, dtu_scan37)", "dtu", max_targets=8, pick="even",
                    fixed_sources=((3, (23, 24, 33)),), masked=True),
    "llff": Protocol("llff", "LLFF poses_bounds.npy captures (fern; ethiopianHead)", "every_8th"),
    "ngp": Protocol("ngp", "instant-ngp transforms.json captures (fox)", "every_8th"),
    "colmap": Protocol("colmap", "COLMAP sparse models", "every_8th"),
    "synth": Protocol("synth", "omnirecon procedural scenes (synth:eval, seeds 900000+)", "test_split"),
}
"""The one protocol per dataset; ``docs/evaluation.md`` has the same table in words."""

CPU_TARGETS = {"blender": 3, "dtu": 4, "llff": 3, "ngp": 3, "colmap": 3, "synth": 2}
"""Targets per scene of the ``cpu`` protocol set (evenly spaced over the full protocol's candidates)."""
PROTOCOL_SETS: dict[str, dict[str, Protocol]] = {
    "full": PROTOCOLS,
    "cpu": {k: replace(p, long_side=64, max_targets=CPU_TARGETS[k], pick="even") for k, p in PROTOCOLS.items()},
}
"""``full``: the published protocols. ``cpu``: the same rules at a 64-px long side (the tiny presets'
training resolution) with fewer targets, so a CPU can score GPNR and IBRNet in minutes; its numbers
are labelled with the set's name and are not comparable with ``full`` numbers."""

FORMAT_PROTOCOL = {"blender": "blender", "ngp": "ngp", "llff": "llff", "dtu_neus": "dtu", "dtu_mvsnet": "dtu",
                   "colmap": "colmap"}
"""Reader name -> protocol (a Blender-layout folder written by ``omnirecon synth`` uses ``synth``)."""

SYNTH_VIEWS = 40
"""Views per held-out procedural scene (5 test targets, 30 train views in the pool)."""


def is_synth(path: Path) -> bool:
    """``path`` holds a scene written by ``omnirecon synth`` (its ``scene.json`` names the generator)."""
    meta = Path(path) / "scene.json"
    if not meta.is_file():
        return False
    return str(read_json(meta).get("generator_version", "")).startswith("omnirecon-synth")


def protocol_for(path: Path, fmt: str, protocol_set: str = "full") -> Protocol:
    """The protocol of the scene at ``path`` read by reader ``fmt``, from set ``protocol_set``."""
    table = PROTOCOL_SETS[protocol_set]
    if fmt == "blender" and path is not None and is_synth(path):
        return table["synth"]
    return table[FORMAT_PROTOCOL[fmt]]


def load_at_resolution(path: Path, long_side: int, background: str = "white", fmt: str = "auto") -> Scene:
    """Read ``path`` with its long side area-downscaled to at most ``long_side`` px, normalised
    (``Scene.normalized``: content centred in the unit sphere, as training does)."""
    if long_side < 8:
        raise InputError(f"resolution must be at least 8 px, got {long_side}", None, "use e.g. 128")
    fmt = detect_format(path) if fmt == "auto" else fmt
    probe = load_scene(path, fmt, ReadOptions(max_views=1))  # one image: the native size
    native = max(probe.width, probe.height)
    scene = load_scene(path, fmt, ReadOptions(downscale=max(1.0, native / long_side), background=background))
    return scene.normalized()


def targets_and_pool(protocol: Protocol, scene: Scene, max_targets: int | None = None) -> tuple[list[int], list[int]]:
    """Target views and the source pool of ``scene`` under ``protocol`` (disjoint, sorted).

    ``max_targets`` overrides the protocol's cap (results then say they are not the protocol's).
    """
    n = len(scene)
    cap = protocol.max_targets if max_targets is None else max_targets
    if protocol.rule == "test_split":
        test = scene.splits.get("test", [])
        if not test:
            raise InputError("scene has no test split", scene.path, f"the {protocol.name} protocol scores the "
                             "test split; give a scene with transforms_test.json")
        candidates = sorted(test)
        pool_from = sorted(scene.splits.get("train") or [i for i in range(n) if i not in set(test)])
    elif protocol.rule == "every_8th":
        candidates = list(range(0, n, 8))
        pool_from = [i for i in range(n) if i % 8]
    else:  # dtu
        fixed = dict(protocol.fixed_sources)[3]
        if n <= max(fixed):
            raise InputError(f"DTU protocol needs views {fixed} but the scene has {n} views", scene.path,
                             "give the full 49-view DTU scan")
        candidates = [i for i in range(n) if i not in fixed]
        pool_from = None
    if cap is not None and len(candidates) > cap:
        if protocol.pick == "first":
            candidates = candidates[:cap]
        else:
            pick = np.unique(np.linspace(0, len(candidates) - 1, cap).round().astype(int))
            candidates = [candidates[i] for i in pick]
    targets = candidates
    pool = [i for i in range(n) if i not in set(targets)] if pool_from is None else pool_from
    pool = [i for i in pool if i not in set(targets)]
    return targets, pool


def view_metric(scene: Scene) -> str:
    """``"angle"`` (around the look-at centre) for object rigs, ``"distance"`` otherwise."""
    return "angle" if scene.rig == "object" else "distance"


def select_sources(scene: Scene, camera, pool: list[int], k: int, center: Tensor | None = None) -> list[int]:
    """The ``k`` views of ``pool`` nearest to ``camera`` (one :class:`Cameras`), nearest first.

    Distance is the angle seen from ``center`` (default: the point closest to all optical axes)
    for object rigs, the distance between camera centres otherwise.
    """
    by = view_metric(scene)
    if by == "angle" and center is None:
        center = closest_point_to_axes(scene.cameras)
    cams = scene.cameras[pool]
    idx = nearest_views(camera.to(dtype=cams.c2w.dtype), cams, k, by=by,
                        center=None if center is None else center.to(cams.c2w))[0]
    return [pool[int(i)] for i in idx]


# ---------------------------------------------------------------------- scenes and models
@dataclass
class EvalScene:
    """A scene ready for evaluation."""

    name: str
    """Unique name in the results (the folder name)."""
    scene: Scene
    """The scene at protocol resolution, normalised."""
    protocol: Protocol
    """Its protocol."""
    path: Path | None = None
    """Where it was read from."""


def synth_eval_paths(spec: str, count: int = 10, cache: Path = Path("outputs/cache"), progress=None) -> list[Path]:
    """Generate (or reuse) the held-out procedural scenes of ``spec`` (``synth:eval[:rig]``).

    Scene ``i`` uses seed ``EVAL_SEEDS[i]`` and is written to ``cache/synth_eval/<rig>_<res>``.
    A cached scene written with other options or by another generator version is regenerated.
    """
    from omnirecon.data.synth.generate import SynthOptions, generate_scene

    parts = spec.split(":")
    rig = parts[2] if len(parts) > 2 else "object"
    if parts[:2] != ["synth", "eval"] or len(parts) > 3 or rig not in ("object", "frontal", "forward"):
        raise InputError(f"bad scene spec {spec!r}", None, "use synth:eval, synth:eval:object, synth:eval:frontal "
                         "or synth:eval:forward")
    if not 1 <= count <= len(EVAL_SEEDS):
        raise InputError(f"--synth-count must be in 1..{len(EVAL_SEEDS)}, got {count}", None, "use e.g. 10")
    res = PROTOCOLS["synth"].long_side
    out = Path(cache) / "synth_eval" / f"{rig}_{res}"
    options = SynthOptions(rig=rig, views=SYNTH_VIEWS, resolution=res)
    task = progress.add_task(f"synth {rig}", total=count) if progress is not None else None
    paths = []
    for seed in EVAL_SEEDS[:count]:
        paths.append(generate_scene(out, seed, options))  # regenerated when its options or version differ
        if task is not None:
            progress.advance(task)
    return paths


def prepare_scenes(specs, count: int = 10, cache: Path = Path("outputs/cache"), progress=None,
                   protocol_set: str = "full") -> list[EvalScene]:
    """Load every scene of ``specs`` (paths, ``synth:eval[:rig]`` or :class:`Scene` objects) under the
    protocols of ``protocol_set``."""
    if protocol_set not in PROTOCOL_SETS:
        raise InputError(f"unknown protocol set {protocol_set!r}", None, f"use one of {', '.join(PROTOCOL_SETS)}")
    paths: list = []
    for spec in specs:
        if isinstance(spec, Scene):
            paths.append(spec)
        elif str(spec).startswith(SYNTH_PREFIX):
            paths.extend(synth_eval_paths(str(spec), count, cache, progress))
        else:
            detect_format(Path(spec))  # fail fast, before any scene is read
            paths.append(Path(spec))
    out, names = [], set()
    for item in paths:
        if isinstance(item, Scene):
            fmt = item.format if item.format in FORMAT_PROTOCOL else "colmap"
            proto = protocol_for(item.path, fmt, protocol_set)
            scene, path = item.normalized(), item.path
        else:
            fmt = detect_format(item)
            proto = protocol_for(item, fmt, protocol_set)
            scene, path = load_at_resolution(item, proto.long_side, proto.background, fmt), item
        base = Path(path).name if path is not None else "scene"
        name, i = base, 1
        while name in names:  # e.g. the same seed from two synth:eval rigs
            i += 1
            name = f"{base}_{i}"
        names.add(name)
        out.append(EvalScene(name, scene, proto, path))
    return out


def load_model(ckpt: Path | None, model: str | None, device: str = "cpu"):
    """The model of ``--ckpt`` or ``--model floor`` (exactly one). Returns ``(model, info)``."""
    from omnirecon.checkpoint import load_checkpoint
    from omnirecon.models.registry import build_model

    if (ckpt is None) == (model is None):
        raise InputError("give exactly one of --ckpt or --model", None,
                         "--ckpt CHECKPOINT_FOLDER for a trained model, or --model floor")
    if model is not None:
        if model != "floor":
            raise InputError(f"--model {model} has no weights", None, "only the non-learned --model floor runs "
                             "without a checkpoint; pass --ckpt for a trained model")
        return build_model("floor").to(device).eval(), {"name": "floor", "preset": "floor", "checkpoint": None}
    if not Path(ckpt).exists():
        raise InputError("checkpoint folder not found", ckpt, "pass e.g. --ckpt checkpoints/omnirecon-tiny")
    net, meta = load_checkpoint(Path(ckpt), device)
    info = {"name": meta["preset"], "preset": meta["preset"], "checkpoint": str(ckpt), "step": meta.get("step")}
    return net.eval(), info


def set_threads(threads: int | None) -> None:
    """Set torch's CPU thread count (``None`` keeps it)."""
    if threads is not None:
        if threads < 1:
            raise InputError(f"--threads must be at least 1, got {threads}", None, "use e.g. 1")
        torch.set_num_threads(threads)


def pick_device(device: str) -> str:
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(f"--device {device} but CUDA is not available", None, "use --device cpu")
    return device


# ---------------------------------------------------------------------- evaluation
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
        seed: Seeds torch before rendering (models are deterministic at test time; recorded).
        protocol_set: ``"full"`` (the published protocols) or ``"cpu"`` (64 px, fewer targets).
        geometry: Also mesh each (scene, K) with :func:`geometry_sources` as the sources
            (``omnirecon mesh``'s protocol) and score the mesh on the targets: Chamfer / F-score
            against a procedural scene's exact mesh, silhouette IoU against the targets' masks.
            Per-target depth errors are reported whenever the model renders depth and the scene
            has ground-truth depth, with or without this flag.

    Returns:
        ``{"provenance", "model", "protocols", "num_views", "scenes": [...], "means": {protocol: {K: {...}}},
        "unavailable": {metric: reason}, "seconds_per_view"}`` (see ``docs/evaluation.md``).
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.progress import TimeRemainingColumn

    from omnirecon import eval_report
    from omnirecon.provenance import provenance

    ks = [int(k) for k in num_views]
    if not ks or min(ks) < 1:
        raise InputError(f"--num-views must be positive integers, got {list(num_views)}", None, "use e.g. 3 10")
    if chunk < 1:
        raise InputError(f"--chunk must be at least 1, got {chunk}", None, "use e.g. 4096")
    if max_targets is not None and max_targets < 1:
        raise InputError(f"--max-targets must be at least 1, got {max_targets}", None, "leave it unset")
    torch.manual_seed(seed)
    model = model.to(device).eval()
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TextColumn("eta"), TimeRemainingColumn())
    with Progress(*columns, disable=not progress, transient=False) as bar:
        prepared = [s for s in scenes if isinstance(s, EvalScene)]
        prepared += prepare_scenes([s for s in scenes if not isinstance(s, EvalScene)], synth_count, cache, bar,
                                   protocol_set)
        jobs, results = _plan(prepared, ks, max_targets)
        check_planned(jobs, results, ks)  # a K that runs nowhere: refused, not empty tables
        total = sum(len(job["targets"]) for job in jobs)
        task = bar.add_task("eval", total=total)
        for job in jobs:
            _run_job(model, job, chunk, device, out if save_images else None, bar, task)
            if geometry:
                _mesh_job(model, job, chunk, device, out)
    result = eval_report.collect(results, jobs, ks, {
        "provenance": provenance(seed=seed, chunk=chunk, eval_device=device),
        "model": model_info or {"name": type(model).__name__},
        "protocol_set": protocol_set,
        "geometry": geometry,
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
            sources = [list(fixed[k]) if k in fixed else select_sources(es.scene, es.scene.cameras[t], pool, k, center)
                       for t in targets]
            jobs.append({"scene": es, "k": k, "targets": targets, "sources": sources, "record": rec})
    return jobs, records


def _run_job(model, job: dict, chunk: int, device: str, out: Path | None, bar, task) -> None:
    """Render and score every target of one (scene, K) job; fills ``job["views"]``."""
    from omnirecon import eval_report

    es: EvalScene = job["scene"]
    scene, k = es.scene, job["k"]
    bar.update(task, description=f"{es.name} K={k}")
    features, key = None, None
    views = []
    for t, src in zip(job["targets"], job["sources"]):
        start = time.perf_counter()
        if tuple(src) != key:  # DTU's fixed sources are encoded once
            features, key = model.encode(Sources.from_scene(scene, src).to(device)), tuple(src)
        camera = scene.cameras[t].to(device=device, dtype=scene.images.dtype)
        rendered = model.render_view(features, camera, chunk=chunk)
        seconds = time.perf_counter() - start
        gt = scene.images[t]
        mask = scene.masks[t] if es.protocol.masked and scene.masks is not None else None
        row = {"index": t, "name": scene.names[t], "sources": src, "seconds": seconds}
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


def _mesh_job(model, job: dict, chunk: int, device: str, out: Path | None) -> None:
    """Mesh one (scene, K) job with :func:`geometry_sources` and score it on the job's targets;
    fills ``job["geometry"]`` (and writes ``<out>/<scene>/k<K>/mesh.ply`` and ``mesh.png``, the mesh
    seen from the first source view at a 512-px long side)."""
    from omnirecon import geometry as geo
    from omnirecon.render.mesh import MeshOptions, mesh_from_model

    es: EvalScene = job["scene"]
    views = geometry_sources(es, job["k"])
    start = time.perf_counter()
    made = mesh_from_model(model, es.scene, views, MeshOptions(chunk=chunk), device)
    seconds = time.perf_counter() - start
    if len(made.mesh.faces) == 0:
        job["geometry"] = {"views": views, "empty": True, "seconds": seconds}
        return
    scored = geo.score_mesh(made, es.scene, job["targets"])
    row = {"views": views, "faces": len(made.mesh.faces), "seconds": seconds}
    if "chamfer" in scored:
        c = scored["chamfer"]
        row.update({"chamfer": c["chamfer"], "accuracy": c["accuracy"], "completeness": c["completeness"],
                    "fscore": c["fscore"], "threshold": c["threshold"], "chamfer_rel": scored["chamfer_rel"]})
    if "mask_iou" in scored:
        row["mask_iou"] = scored["mask_iou"]["mean"]
    if "rendered_depth" in scored:
        row["fused_depth_abs_rel"] = scored["rendered_depth"]["abs_rel"]
    if out is not None:
        folder = Path(out) / es.name / f"k{job['k']}"
        from omnirecon.render.mesh import export_mesh, to_input_frame

        export_mesh(to_input_frame(made.mesh, es.scene.to_input), [folder / "mesh.ply"])
        cam = es.scene.cameras[views[0]]
        geo.save_picture(folder / "mesh.png", made.mesh, cam.rescaled(max(1.0, 512 / max(cam.width, cam.height))))
    job["geometry"] = row


# ---------------------------------------------------------------------- CLI
def default_name(ckpt: Path | None, model_name: str) -> str:
    """Output name: ``<run>_<checkpoint>`` for ``.../<run>/checkpoints/<checkpoint>``, else the folder or model name."""
    if ckpt is None:
        return model_name
    ckpt = Path(ckpt).resolve()
    return f"{ckpt.parent.parent.name}_{ckpt.name}" if ckpt.parent.name == "checkpoints" else ckpt.name


@dataclass
class EvalConfig:
    """Evaluate a checkpoint (or the non-learned plane-sweep floor) on held-out views: PSNR, SSIM,
    ST-LPIPS (and LPIPS where its weights are on the machine), per scene and averaged, under the
    fixed protocols of docs/evaluation.md. Writes results.json, results.md and one
    GT | render | error panel per target view."""

    scenes: tuple[str, ...] = (SYNTH_PREFIX,)
    """Scene folders (any supported format) and/or synth:eval[:object|frontal|forward] (the held-out
    procedural set, generated on first use)."""
    ckpt: Path | None = None
    """Checkpoint folder written by `omnirecon train` (holds meta.json and model.safetensors)."""
    model: Literal["floor"] | None = None
    """Evaluate a non-learned model instead of a checkpoint: `floor` is the plane-sweep baseline."""
    num_views: tuple[int, ...] = (3, 10)
    """Source-view counts K to evaluate (3 and 10 are the standard settings)."""
    out: Path | None = None
    """Output folder (default: outputs/eval/<model name>)."""
    synth_count: int = 10
    """Scenes in the synth:eval set (seeds 900000, 900001, ...)."""
    chunk: int | None = None
    """Rays rendered per chunk (default: from the free memory, at most 4096; a note when above 25% of RAM)."""
    device: str = "auto"
    """cpu, cuda or auto (cuda when available)."""
    max_targets: int | None = None
    """Score at most this many targets per scene instead of the protocol's choice (quick checks;
    results are marked as not following the protocol)."""
    save_images: bool = True
    """Write a GT | render | |error| panel per target."""
    cache: Path = Path("outputs/cache")
    """Where the synth:eval scenes are generated."""
    threads: int | None = None
    """torch CPU threads (default: torch's choice). Use 1 when other jobs share the cores: on a busy
    2-core machine 2 threads ran the floor 6x slower than 1."""
    protocol_set: Literal["full", "cpu"] = "full"
    """``full``: the published protocols (128 px); ``cpu``: the same rules at 64 px with fewer targets
    (the CPU benchmark of the tiny presets; not comparable with ``full``)."""
    geometry: bool = False
    """Also extract a mesh per scene and K (`omnirecon mesh`'s protocol; sources: DTU's 23 24 33 or K
    evenly spaced pool views) and score it: Chamfer / F-score against a procedural scene's exact
    mesh, silhouette IoU on the targets' masks. Per-target depth errors need no flag."""

    def main(self) -> None:
        prepare_out(self.out)  # writable, stale temporaries gone: before any work
        self.chunk = pick_chunk(self.chunk)  # None: from the free memory
        set_threads(self.threads)
        device = pick_device(self.device)
        net, info = load_model(self.ckpt, self.model, device)
        out = self.out or Path("outputs/eval") / default_name(self.ckpt, info["name"])
        if out.exists() and not out.is_dir():
            raise InputError("output path exists and is not a folder", out, "pass a folder for --out")
        result = evaluate(net, list(self.scenes), self.num_views, out, model_info=info, chunk=self.chunk,
                          device=device, max_targets=self.max_targets, synth_count=self.synth_count,
                          cache=self.cache, save_images=self.save_images, protocol_set=self.protocol_set,
                          geometry=self.geometry)
        from omnirecon.eval_report import summary_lines

        for line in summary_lines(result):
            print(line)
        print(f"wrote {out / 'results.json'} and {out / 'results.md'}")
