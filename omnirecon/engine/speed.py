"""``omnirecon bench``: frames per second of Omni-Recon's real-time mesh path against its volumetric
path: one model, one scene, one resolution, one run.

    omnirecon bench                          # 512x512 targets, 3 source views, median of 30 frames
    omnirecon bench --threads 1              # one torch thread and one llvmpipe thread
    omnirecon bench --quick                  # 128x128, 3 frames, a 64-ray volumetric batch (tests)
    python -m bench mesh_fps ...             # the same, writing bench/results/mesh_fps.json
    omnirecon bench --scene S --mesh M       # a capture's own mesh (e.g. fern's `omnirecon mesh`) at its photos' size

Scene: a procedural scene (``--seed``), normalised as in training, rendered with its exact mesh
(the triangles its images were rendered from); or, with ``--scene`` and ``--mesh``, a capture and its mesh
file (targets its test views at the photos' size). Model: the shipped ``omnirecon-tiny`` when it exists,
else a randomly initialised ``omnirecon-tiny`` (the JSON says which; speed does not depend on the
weights). Sources: the ``--views`` training views nearest to the first target; source features are
encoded once (:class:`~omnirecon.mesh.ibr.MeshRenderer`), as both paths allow.

* **Mesh path**: :meth:`MeshRenderer.render` of a full frame (``extras=False``: :meth:`MeshRenderer.frame`,
  depth pass -> one surface point per pixel -> appearance branch -> image), the camera moving every frame
  through the scene's held-out views; warm-up, then the median over ``--frames`` frames; blending without
  the visibility test (the renderer's default). Also reported: the rasterization alone (the depth pass the
  frame uses, the compact surface pass of ``render`` with extras, and the full G-buffer with ids,
  barycentrics and normals) and the same path with the per-source visibility test (the web viewer's
  default).
* **Volumetric path**: ``model.render_rays`` (coarse + fine passes, the geometry branch) on batches of
  ``--rays`` random pixels of the same target view at the same resolution; a frame of ``W x H`` rays
  would take ``W H / (rays/s)`` seconds, so its FPS is *extrapolated from rays/s* (a full 512^2 frame
  takes minutes on a CPU). ``render_view`` renders exactly such batches in sequence.

CUDA is synchronised around every timed call when used. Writes ``--out`` (JSON with a provenance
header; ``omnirecon bench``: ``outputs/bench/mesh_fps.json``).
"""

from __future__ import annotations

import os
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

from omnirecon.cameras import nearest_views
from omnirecon.data import load_scene
from omnirecon.data.io import write_json
from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.engine.checkpoint import load_checkpoint
from omnirecon.engine.lod import choose_level_of_detail
from omnirecon.engine.machine import DeviceConfig, ShippedCheckpoint, pick_device
from omnirecon.engine.scenes import load_at_resolution, photo_side
from omnirecon.engine.shipped import checkpoint_folder, shipped_folder
from omnirecon.errors import InputError
from omnirecon.mesh.files import read_mesh
from omnirecon.mesh.ibr import (
    MeshRenderer,
    MeshRenderOptions,
    level_of_detail,
    realtime_setting,
    video_options,
)
from omnirecon.models.registry import build_model
from omnirecon.options import ImageSize, MeshFile, Overwrites, QuickRun, Seeded, check_options, command_defaults
from omnirecon.provenance import provenance
from omnirecon.rays import Rays, Sources
from omnirecon.scene_kind import scene_kind

GOALS = {"cpu_fps_512": 30.0, "ratio": 1000.0, "gpu_fps_800x600": 500.0}
"""Speed goals the record is checked against (targets, not measurements): frames per second at 512x512 on the
2-core CPU, the mesh path's speed-up over the volumetric path, frames per second at 800x600 on a GPU."""


@dataclass
@command_defaults(resolution=512)
class BenchConfig(Overwrites, Seeded, ShippedCheckpoint, ImageSize, MeshFile, QuickRun, DeviceConfig):
    """Frames per second of Omni-Recon's mesh path and of its volumetric path in one run (warm-up,
    median of N frames, same resolution, same source views, CUDA synchronised), and their ratio."""

    size: tuple[int, int] | None = None
    """Target width and height instead of --resolution, e.g. a capture's own photo size (fern: 504 378,
    DTU: 400 300); the procedural sources are then rendered at the larger side too."""
    source_resolution: int = 128
    """Procedural scene image size (the sources)."""
    views: int = 3
    """Source views K."""
    frames: int = 30
    """Timed mesh-path frames (median)."""
    warmup: int = 3
    """Untimed frames before timing."""
    rays: int = 1024
    """Rays per timed volumetric batch."""
    volume_repeats: int = 3
    """Timed volumetric batches (median)."""
    workers: int | None = None
    """Mesh path: threads that shade chunks side by side (`MeshRenderOptions.workers`), each op on one torch
    thread (default: --threads; 1 when --threads is not given). The volumetric path keeps --threads torch
    threads."""
    scene: Path | None = None
    """A real scene folder to time instead of the procedural scene, with --mesh (e.g. fern and its
    `omnirecon mesh` file): read with its long side at --size's (default: the photos' own, at most 512),
    targets its test views at that size, sources the --views training views nearest the first target."""
    realtime: bool = False
    """Time the path the real-time videos take (``reconstruct``'s, ``demo``'s): the scene kind's blend, fill and sources
    (:func:`omnirecon.mesh.ibr.realtime_setting`: the angle blend over every training view on object captures, ranking
    each chunk's candidates (`REALTIME_FRAME_GRID`), the network's over the 6 nearest elsewhere) with the occlusion test,
    at the face budget and sources they draw (:func:`omnirecon.engine.lod.choose_level_of_detail`: at most
    :data:`omnirecon.mesh.ibr.REALTIME_FACE_BUDGET` faces, fewer faces and sources and the network's MLP every 2 px
    where left-out photos show no loss),
    instead of the paper's network blend over --views sources without the test on the full mesh."""
    face_budget: int | None = None
    """Faces drawn at most (the mesh decimated once before timing, `MeshRenderOptions.face_budget`; 0: the full mesh;
    default: with --realtime the budget the videos draw, chosen per mesh on left-out photos, else 0)."""
    out: Path = Path("outputs") / "bench" / "mesh_fps.json"
    """JSON result file."""

    def check(self) -> BenchConfig:
        """Validated settings, with ``--quick`` applied."""
        check_options("bench", self)  # --resolution, --size, --views, --frames...: omnirecon/options.py
        if (self.scene is None) != (self.mesh is None):
            raise InputError("--scene and --mesh go together", self.scene or self.mesh,
                             "pass both, e.g. --scene ../shared/data/llff/fern --mesh outputs/mesh/fern.ply")
        if self.size and not self.quick:
            return replace(self, source_resolution=max(self.size))
        if self.quick:
            return replace(self, resolution=128, source_resolution=64, frames=3, warmup=1, rays=64, volume_repeats=1)
        return self


def procedural_scene(seed: int, resolution: int):
    """The procedural scene ``seed`` (16 views at ``resolution``, normalised) and its exact mesh in that frame."""
    import numpy as np
    import trimesh

    folder = Path(tempfile.mkdtemp(prefix="mesh_fps_"))
    try:
        scene_dir = generate_scene(folder, seed, SynthOptions(rig="object", views=16, resolution=resolution))
        scene = load_scene(scene_dir).normalized()
        raw = trimesh.load(scene.mesh_path, process=False, force="mesh")
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    T = scene.mesh_to_scene.double().numpy()
    return scene, trimesh.Trimesh(np.asarray(raw.vertices) @ T[:3, :3].T + T[:3, 3], np.asarray(raw.faces),
                                  process=False)


def target_camera(camera, width: int, height: int):
    """``camera`` (square) scaled to ``max(width, height)`` and centre-cropped to ``width x height``: the
    same view at a photo's aspect ratio."""
    side = max(width, height)
    c = camera.rescaled(side / camera.width)
    return replace(c, cx=c.cx - (side - width) / 2, cy=c.cy - (side - height) / 2, width=width, height=height)


def measure(cfg: BenchConfig) -> dict:
    """Time both paths as ``cfg`` says; writes ``cfg.out`` and returns its record."""
    args = cfg.check()
    if args.threads is not None:  # llvmpipe reads it when the driver loads: before any GL context
        os.environ["LP_NUM_THREADS"] = str(args.threads)
    import torch

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    device = pick_device(args.device)

    def sync() -> None:
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    cpu_times: dict[int, list[float]] = {}

    def timed(fn, repeats: int, warmup: int) -> list[float]:
        """Wall seconds per call; the process CPU seconds per call go to ``cpu_times[id(list)]``."""
        for _ in range(warmup):
            fn()
        times, cpu = [], []
        for _ in range(repeats):
            sync()
            start, start_cpu = time.perf_counter(), time.process_time()
            fn()
            sync()
            times.append(time.perf_counter() - start)
            cpu.append(time.process_time() - start_cpu)
        cpu_times[id(times)] = cpu
        return times

    def cpu_ms(times: list[float]) -> float:
        return round(1000 * statistics.median(cpu_times[id(times)]), 2)

    torch.manual_seed(args.seed)
    ckpt = checkpoint_folder(args.ckpt)  # a path, or a shipped name such as omnirecon-tiny
    if (ckpt / "meta.json").is_file():
        model, meta = load_checkpoint(ckpt, device)
        if not model.capabilities.appearance:
            raise InputError(f"the mesh path needs an Omni-Recon checkpoint, got preset {meta['preset']}", args.ckpt,
                             "pass checkpoints/omnirecon-tiny or another omnirecon-* checkpoint")
        home = shipped_folder().parent  # the checkout in a source checkout: "checkpoints/omnirecon-tiny"
        shown = ckpt.resolve().relative_to(home) if ckpt.resolve().is_relative_to(home) else ckpt
        weights = f"checkpoint {shown} (step {meta.get('step')})"
    else:
        model = build_model("omnirecon-tiny").to(device)
        weights = "random init (no shipped checkpoints/omnirecon-tiny); speed does not depend on the weights"
    model.eval()

    if args.scene is not None:  # a real capture and its mesh, at the photos' size
        scene = load_at_resolution(args.scene, max(args.size) if args.size else photo_side(args.scene))
        mesh = read_mesh(args.mesh, scene.to_input)
        width, height = scene.width, scene.height
        held_out = scene.splits.get("test") or [0]
        train = [i for i in (scene.splits.get("train") or range(len(scene))) if i not in held_out]
        targets = [scene.cameras[i].to(device=device, dtype=torch.float32) for i in held_out]
        by = "distance" if scene_kind(scene).forward else "angle"
    else:
        scene, mesh = procedural_scene(args.seed, args.source_resolution)
        held_out = scene.splits.get("test", []) + scene.splits.get("val", [])
        train = scene.splits["train"]
        width, height = args.size or (args.resolution, args.resolution)
        targets = [target_camera(scene.cameras[i], width, height).to(device=device, dtype=torch.float32)
                   for i in held_out]
        by = "angle"
    setting = realtime_setting(scene) if args.realtime else None
    lod = choose_level_of_detail(model, mesh, scene, setting, train) if args.realtime and args.face_budget is None else None
    setting = lod.setting(setting) if lod else setting  # the sources per frame and MLP stride the videos blend with
    count = (setting["sources"] or len(train)) if setting else args.views
    pick = nearest_views(scene.cameras[held_out[:1]], scene.cameras[train], min(count, len(train)), by=by)[0]
    views = [train[i] for i in pick.tolist()]
    sources = Sources.from_scene(scene, views).to(device)
    budget = args.face_budget if args.face_budget is not None else (lod.face_budget if lod else 0)
    start = time.perf_counter()
    drawn = lod.drawn(mesh, scene.cameras[train]) if lod else level_of_detail(mesh, budget)  # once, for every renderer
    decimate_s = time.perf_counter() - start
    background = scene.background or (1, 1, 1)

    # ---------------------------------------------------------------- mesh path
    workers = args.workers or args.threads or 1
    torch_threads = torch.get_num_threads()
    if workers > 1:
        torch.set_num_threads(1)  # parallel over chunks, not inside each op (MeshRenderOptions.workers)
    start = time.perf_counter()
    opts = (video_options(setting, background, workers, face_budget=0) if setting else  # decimated above
            MeshRenderOptions(background=background, workers=workers))
    renderer = MeshRenderer(model, drawn, sources, opts)
    sync()
    setup_s = time.perf_counter() - start
    frame = [0]

    def next_camera():
        frame[0] += 1
        return targets[frame[0] % len(targets)]

    mesh_times = timed(lambda: renderer.render(next_camera(), extras=False), args.frames, args.warmup)
    depth_times = timed(lambda: renderer.rasterizer.depth(next_camera()), args.frames, args.warmup)
    surface_times = timed(lambda: renderer.rasterizer.surface(next_camera()), args.frames, args.warmup)
    gbuffer_times = timed(lambda: renderer.rasterizer.rasterize(next_camera(), normals="face"), args.frames,
                          args.warmup)
    coverage = statistics.mean(len(renderer.rasterizer.surface(c).pixels) / (c.width * c.height) for c in targets)
    with MeshRenderer(model, drawn, sources, replace(opts, visibility=True)) as vis_renderer:
        vis_times = timed(lambda: vis_renderer.render(next_camera(), extras=False), args.frames, args.warmup)
    backend = renderer.rasterizer.backend
    renderer.close()
    with torch.no_grad():
        features = model.encode(sources)  # the volumetric path reads the feature volume (the mesh renderer's has none)
    torch.set_num_threads(torch_threads)

    # ---------------------------------------------------------------- volumetric path
    cam = targets[0]
    g = torch.Generator().manual_seed(args.seed)
    uv = torch.rand(args.rays, 2, generator=g) * torch.tensor([cam.width, cam.height], dtype=torch.float32)
    rays = Rays.from_pixels(cam, torch.zeros(args.rays, dtype=torch.long, device=device), uv.to(device))
    with torch.no_grad():
        volume_times = timed(lambda: model.render_rays(features, rays), args.volume_repeats, 1)

    pixels = width * height
    mesh_s = statistics.median(mesh_times)
    volume_s = statistics.median(volume_times)
    rays_per_s = args.rays / volume_s
    mesh_fps = 1.0 / mesh_s
    volume_fps = rays_per_s / pixels
    result = {
        "provenance": provenance(seed=args.seed, lp_num_threads=os.environ.get("LP_NUM_THREADS")),
        "config": {"quick": args.quick, "device": device, "torch_threads": torch.get_num_threads(),
                   "mesh_path_workers": workers, "mesh_path_torch_threads": 1 if workers > 1 else torch_threads,
                   "llvmpipe_threads": os.environ.get("LP_NUM_THREADS", "default (all cores)"),
                   "rasterizer": backend, "resolution": [width, height],
                   "source_views": args.views, "source_resolution": [scene.width, scene.height],
                   "frames": args.frames, "warmup": args.warmup},
        "model": {"preset": "omnirecon-tiny", "weights": weights,
                  "samples_per_ray": model.cfg.coarse_samples + model.cfg.fine_samples},
        "scene": {**({"kind": "procedural", "seed": args.seed, "rig": "object", "mesh": "exact procedural mesh"}
                     if args.scene is None else {"kind": "capture", "path": str(args.scene), "rig": scene.rig,
                                                 "mesh": str(args.mesh)}),
                  "frame": "normalised (training frame)", "faces": len(mesh.faces), "vertices": len(mesh.vertices),
                  "faces_drawn": len(drawn[1]), "face_budget": budget, "decimate_s": round(decimate_s, 2),
                  "lod": None if lod is None else lod.record(),
                  "blend": setting or "network (the paper's), no occlusion test",
                  "source_view_ids": views, "target_view_ids": held_out, "coverage": round(coverage, 4)},
        "mesh": {"resolution": [width, height], "fps": round(mesh_fps, 3),
                 "median_ms": round(1000 * mesh_s, 2), "min_ms": round(1000 * min(mesh_times), 2),
                 "cpu_ms": cpu_ms(mesh_times), "fps_from_cpu_time": round(1000 / cpu_ms(mesh_times), 3),
                 "depth_pass_ms": round(1000 * statistics.median(depth_times), 2),
                 "depth_pass_cpu_ms": cpu_ms(depth_times),
                 "surface_pass_ms": round(1000 * statistics.median(surface_times), 2),
                 "surface_pass_cpu_ms": cpu_ms(surface_times),
                 "gbuffer_ms": round(1000 * statistics.median(gbuffer_times), 2),
                 "gbuffer_cpu_ms": cpu_ms(gbuffer_times),
                 "shading_ms": round(1000 * (mesh_s - statistics.median(depth_times)), 2),
                 "blending": "without the visibility test (MeshRenderOptions' default, as `omnirecon render`); the "
                             "web viewer (`omnirecon export`) starts with it on: visibility_fps",
                 "visibility_fps": round(1.0 / statistics.median(vis_times), 3),
                 "visibility_median_ms": round(1000 * statistics.median(vis_times), 2),
                 "setup_s": round(setup_s, 3),
                 "note": "full frame per call (MeshRenderer.frame): depth pass + unprojection, fill, appearance "
                         "branch and image rows in parallel chunks; source features encoded once per scene (setup_s); "
                         "depth_pass_ms is the rasterization inside it, surface_pass_ms the compact (world, depth) pass "
                         "the extras path uses, gbuffer_ms "
                         "the full G-buffer (ids, barycentrics, depth, points, face normals). *_ms are wall-clock "
                         "medians; *_cpu_ms the process CPU time per call (all threads, llvmpipe's included), "
                         "which other processes on the same cores do not inflate"},
        "volumetric": {"resolution": [width, height], "rays_per_batch": args.rays,
                       "batches": args.volume_repeats, "median_batch_s": round(volume_s, 4),
                       "rays_per_s": round(rays_per_s, 2), "fps_equivalent": round(volume_fps, 6),
                       "cpu_s_per_batch": round(statistics.median(cpu_times[id(volume_times)]), 4),
                       "note": f"model.render_rays on {args.rays} random pixels of the same target at the same "
                               "resolution; FPS extrapolated as (rays/s) / (W H), not a full frame"},
        "ratio": float(f"{round(mesh_fps, 3) / (round(volume_fps, 6) or volume_fps):.4g}"),  # of the numbers written
        "goals": GOALS,
    }
    result["provenance"]["loadavg_1min_end"] = round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
    write_json(args.out, result)
    print(f"mesh path {width}x{height}, {len(drawn[1]):,} of {len(mesh.faces):,} faces, {len(views)} sources "
          f"({'the real-time blend, ' if setting else ''}{backend}, {device}, "
          f"{workers} shading threads): {mesh_fps:.1f} FPS ({1000 * mesh_s:.1f} ms wall, "
          f"{result['mesh']['cpu_ms']:.1f} ms CPU; depth pass {result['mesh']['depth_pass_ms']:.1f} ms, surface pass "
          f"{result['mesh']['surface_pass_ms']:.1f} ms, full G-buffer {result['mesh']['gbuffer_ms']:.1f} ms; "
          f"with visibility {result['mesh']['visibility_fps']:.1f} FPS) | volumetric {rays_per_s:.0f} rays/s = "
          f"{volume_fps:.5f} FPS | ratio {result['ratio']:.0f}x -> {args.out}", file=sys.stderr)
    return result
