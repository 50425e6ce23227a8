"""Level of detail of the real-time mesh path: frame time and held-out PSNR per face budget on the meshes users get.

    python -m bench mesh_lod                                  # fox, fern, the demo scene, lund
    python -m bench mesh_lod --scenes fox --mesh fox=/tmp/fox.ply --budgets 0 200000 100000

Per scene: the mesh ``reconstruct`` builds (``omnirecon mesh --ckpt checkpoints/omnirecon-tiny --views all``,
``reconstruct``'s mesh stage; built into ``outputs/bench/mesh_lod/<scene>.ply`` unless ``--mesh`` names one), then for
the reference path (the full mesh, every source ranked at every point, the torch shader: what the videos drew before)
and each face budget (``MeshRenderOptions.face_budget``, 0: the full mesh) with the candidate sources (``--grid``,
``MeshRenderOptions.frame_grid``) and each frame shader of ``--shader`` (``MeshRenderOptions.shader``; ``auto``: the GL
pass):

* **speed**: ``MeshRenderer.render(extras=False)`` (the frame path) of the held-out views at the photos' size (the
  demo scene at the demo's 256 px), blended as the real-time videos blend (:func:`omnirecon.mesh.ibr.realtime_setting`
  of the scene, the occlusion test on; the angle blend over every training view, the network's over the 6 nearest;
  with ``--record NAME=curve.json``, the blend that finetune record scored, as ``reconstruct`` draws it),
  ``--threads`` shading workers with one torch thread each and as many llvmpipe threads; median wall and process-CPU
  ms of ``--frames`` frames after a warm-up, the calling thread's CPU ms (the frame's serial part), the same frames
  as a stream (``MeshRenderer.frames``: a frame ahead, each frame's GL pass shaded while the next one's depth pass is
  drawn; what the videos render), the depth pass alone, the decimation's seconds; each timing the median of
  ``--rounds`` rounds, each round timing every row of the scene in turn (so that the machine's drift over minutes
  falls on every row alike). The machine may be shared: the largest 1-minute load average of a row's rounds is
  recorded beside it;
* **quality**: held-out PSNR (whole image, at most ``--max-views`` test views) through the same blend, each view from
  its own nearest sources, and its loss against the reference path's (the demo scene: timed at 256 px, scored at its
  128-px images).

Then the level :func:`omnirecon.engine.lod.choose_level_of_detail` chooses (its sources per frame and weight stride,
or the angle blend's sources per point),
and, where it draws only the faces the photos see, that level so (``photographed``: the faces the training views see,
:func:`omnirecon.mesh.ibr.photographed_faces`). With the angle blend and ``--proposed N ...``, that level again with
``N`` candidate sources proposed per grid point beyond the point's own (``GLBlend.PROPOSED``; every row records the
count it ran with as ``candidates_proposed``), a row each.

``checkpoints/omnirecon-tiny`` untuned (the frame time does not depend on the weights). Writes
``bench/results/mesh_lod.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
SCENES = {"fox": "instant_ngp/fox", "fern": "llff/fern", "demo": None, "lund": None}
LUND = ROOT / "outputs" / "cache" / "extrapolation" / "lund_scene"
"""The street photos posed as ``python -m bench extrapolation`` poses them (its cache, when it is there)."""
LUND_PHOTOS = SHARED / "photos" / "lund"
BUDGETS = (0, 300_000, 200_000, 150_000, 100_000, 50_000, 25_000)
DEMO_SIDE = 256


def scene_path(name: str, work: Path) -> Path | None:
    """The scene folder of ``name`` (the demo's procedural scene generated into ``work``; lund: the extrapolation
    bench's posed copy when it is cached, else the photos posed into ``work`` as ``reconstruct`` poses them, i.e.
    ``omnirecon process`` with its defaults at 2 threads; None without the photos)."""
    if name == "demo":
        from omnirecon.data.synth.generate import SynthOptions, generate_scene
        from omnirecon.workflows.demo import DEMO_SEED

        return generate_scene(work / "demo_scene", DEMO_SEED, SynthOptions(rig="object", views=24, resolution=128))
    if name == "lund":
        if LUND.is_dir():
            return LUND
        posed = work / "lund_scene"
        if not (posed / "sparse").is_dir() and LUND_PHOTOS.is_dir():
            from omnirecon.capture.colmap_sfm import SfmOptions
            from omnirecon.capture.process import process

            process(LUND_PHOTOS, posed, SfmOptions(threads=2), overwrite=True)
        return posed if (posed / "sparse").is_dir() else None
    return SHARED / SCENES[name]


def build_mesh(path: Path, out: Path, threads: int) -> Path:
    """``reconstruct``'s mesh stage on ``path`` (every view, 3 sources each, the photos' size) into ``out``."""
    from omnirecon.engine.scenes import photo_side
    from omnirecon.workflows.mesh import MeshConfig, run_mesh

    if not out.is_file():
        run_mesh(MeshConfig(scene=path, ckpt=ROOT / "checkpoints" / "omnirecon-tiny", views=("all",), num_views=3,
                            out=(out,), resolution=photo_side(path), threads=threads))
    return out


def timed(fn, cams: list, frames: int) -> tuple[float, float, float]:
    """Median wall, process-CPU and calling-thread CPU milliseconds of ``fn(camera)`` over ``frames`` calls (one
    warm-up). The calling thread's CPU is the frame's serial part (the GL passes' front end, the fill, the candidates,
    the blur at depth edges): on idle cores the wall time cannot fall below it."""
    fn(cams[0])
    wall, cpu, main = [], [], []
    for i in range(frames):
        start, start_cpu, start_main = time.perf_counter(), time.process_time(), time.thread_time()
        fn(cams[i % len(cams)])
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
        main.append(time.thread_time() - start_main)
    return tuple(round(1000 * statistics.median(x), 2) for x in (wall, cpu, main))


def streamed(renderer, cams: list, frames: int) -> tuple[float, float]:
    """Wall and process-CPU milliseconds per frame of ``frames`` frames rendered as a stream
    (:meth:`~omnirecon.mesh.ibr.MeshRenderer.frames`: a frame ahead, as the videos render)."""
    start, start_cpu = time.perf_counter(), time.process_time()
    for _ in renderer.frames(cams[i % len(cams)] for i in range(frames)):
        pass
    return (round(1000 * (time.perf_counter() - start) / frames, 2),
            round(1000 * (time.process_time() - start_cpu) / frames, 2))


TIMINGS = ("frame_ms", "frame_cpu_ms", "frame_main_cpu_ms", "stream_ms", "stream_cpu_ms", "depth_pass_ms",
           "depth_pass_cpu_ms")
"""A row's timings (ms): each the median of its rounds (:func:`run_scene`)."""


def measure_budget(model, mesh, scene, setting: dict, budget: int, grid: int, side: int, args,
                   shader: str = "auto", score: bool = True, photographed: bool = False,
                   proposed: int | None = None, decimator: str = "fast") -> dict:
    """Speed and held-out PSNR of the real-time path on ``mesh`` at face budget ``budget``, candidate grid ``grid``
    (``MeshRenderOptions.frame_grid``) and frame shader ``shader`` (``MeshRenderOptions.shader``; module docstring), timed
    at ``side`` px long side, scored at the scene's (without ``score``: the timings only); with ``photographed``, only
    the faces the training views see are drawn (:func:`omnirecon.mesh.ibr.level_of_detail` with ``photos``); with
    ``proposed``, the angle blend's candidate tiles take that many sources per grid point beyond its own
    (``GLBlend.PROPOSED``, restored after); ``decimator``: the quadric edge collapse (``level_of_detail``)."""
    import torch

    from omnirecon.render.glblend import GLBlend

    if proposed is not None:
        shipped, GLBlend.PROPOSED = GLBlend.PROPOSED, proposed
        try:
            return measure_budget(model, mesh, scene, setting, budget, grid, side, args, shader, score, photographed,
                                  decimator=decimator)
        finally:
            GLBlend.PROPOSED = shipped

    from omnirecon import metrics
    from omnirecon.engine.views import select_sources
    from omnirecon.mesh.frames import ViewCache
    from omnirecon.mesh.ibr import level_of_detail, realtime_options

    train = scene.splits.get("train") or list(range(len(scene)))
    start = time.perf_counter()
    vertices, faces = level_of_detail(mesh, budget, scene.cameras[train] if photographed else None, decimator)
    decimate_s = time.perf_counter() - start
    bg = tuple(scene.background) if scene.background is not None else (1.0, 1.0, 1.0)
    opts = realtime_options(setting, background=bg, visibility=True, workers=args.threads, frame_grid=grid, shader=shader)
    test = (scene.splits.get("test") or [0])[:args.max_views]
    cams = [scene.cameras[i].to(dtype=torch.float32) for i in test]
    timed_cams = [c.rescaled(side / max(c.width, c.height)) for c in cams]  # the demo: its 256-px frames
    k = min(setting["sources"] or len(train), len(train))
    picks = {t: sorted(select_sources(scene, cams[j], train, k)) for j, t in enumerate(test)}
    psnr = []
    with ViewCache(model, (vertices, faces), scene, opts) as cache:
        with cache.renderer(picks[test[0]]) as r:
            load = os.getloadavg()[0]
            wall, cpu, main = timed(lambda c: r.render(c, extras=False), timed_cams, args.frames)
            stream_wall, stream_cpu = streamed(r, timed_cams, args.frames)
            depth_wall, depth_cpu, _ = timed(lambda c: r.rasterizer.depth(c), timed_cams, args.frames)
            load = round(max(load, os.getloadavg()[0]), 2)
            used = "gl" if r._gl_blend() is not None else "torch"
        for j, t in enumerate(test if score else ()):
            with cache.renderer(picks[t]) as r:
                rgb = r.render(cams[j], extras=False)["rgb"].float().clamp(0, 1)
            psnr.append(metrics.psnr(rgb, scene.images[t].float()))
    row = {"face_budget": budget, "frame_grid": grid, "shader": used, "candidates_proposed": GLBlend.PROPOSED,
           "decimator": decimator, "faces": int(len(faces)),
           "vertices": int(len(vertices)), "decimate_s": round(decimate_s, 2), "frame_ms": wall, "frame_cpu_ms": cpu,
           "frame_main_cpu_ms": main, "stream_ms": stream_wall, "stream_cpu_ms": stream_cpu, "depth_pass_ms": depth_wall,
           "depth_pass_cpu_ms": depth_cpu, "loadavg_1min": load}
    return {**row, "psnr": round(float(statistics.mean(psnr)), 3), "psnr_views": len(psnr)} if score else row


def _rates(row: dict) -> dict:
    """``row`` with its frame rates from its timings."""
    return {**row, "fps": round(1000 / row["frame_ms"], 2), "stream_fps": round(1000 / row["stream_ms"], 2),
            "fps_from_cpu_time": round(1000 / row["frame_cpu_ms"], 2)}


def run_scene(name: str, model, args) -> dict | None:
    import torch

    from omnirecon.engine.lod import choose_level_of_detail
    from omnirecon.engine.scenes import load_at_resolution, photo_side
    from omnirecon.mesh.files import read_mesh
    from omnirecon.mesh.ibr import realtime_setting

    work = ROOT / "outputs" / "bench" / "mesh_lod"
    work.mkdir(parents=True, exist_ok=True)
    path = scene_path(name, work)
    if path is None:
        print(f"{name}: no photos at {LUND_PHOTOS}; left out")
        return None
    given = dict(m.split("=", 1) for m in args.mesh)
    mesh_file = Path(given[name]) if name in given else build_mesh(path, work / f"{name}.ply", 1)
    torch.set_num_threads(args.threads)
    side = DEMO_SIDE if name == "demo" else photo_side(path)
    scene = load_at_resolution(path, side)
    mesh = read_mesh(mesh_file, scene.to_input)
    records = dict(m.split("=", 1) for m in args.record)
    record = json.loads(Path(records[name]).read_text()) if name in records else None
    setting = realtime_setting(scene, record)  # finetune's blend where a record is given, as reconstruct draws
    lod = choose_level_of_detail(model, mesh, scene, setting, scene.splits.get("train") or list(range(len(scene))))
    print(name, lod.line(), flush=True)
    torch.set_num_threads(1)  # the shading workers parallelise (MeshRenderOptions.workers)
    budgets = sorted({*args.budgets, lod.face_budget}, reverse=True)  # the chosen budget always has a row
    runs = [(0, 0, "torch")] + [(b, args.grid, sh) for b in budgets if 0 < b < len(mesh.faces) for sh in args.shader]
    specs = [(setting, budget, grid, shader, {}) for budget, grid, shader in dict.fromkeys(runs)]  # the reference first
    dec = {"decimator": lod.decimator} if lod.decimator != "fast" else {}  # the chosen level's own collapse
    per_point = {"angle_sources": lod.angle_sources} if lod.angle_sources is not None else {}
    if lod.sources is not None or lod.weight_stride > 1 or dec or per_point:  # the chosen level as the videos draw
        chosen = lod.setting(setting)  # it: its budget, fewer sources (per frame, per point), the MLP's stride (and the
        for stride in dict.fromkeys((1, lod.weight_stride)):  # same at every pixel, to compare)
            specs += [({**chosen, "weight_stride": stride}, lod.face_budget, args.grid, shader,
                       {"sources": chosen["sources"] if lod.sources is not None else None, "weight_stride": stride,
                        **dec, **per_point}) for shader in args.shader]
    if lod.photographed:  # and drawing only the faces the photos (the training views) see
        chosen = lod.setting(setting)
        specs += [(chosen, lod.face_budget, args.grid, shader,
                   {"sources": chosen["sources"] if lod.sources is not None else None,
                    "weight_stride": lod.weight_stride, "photographed": True, **dec, **per_point})
                  for shader in args.shader]
    if setting["blend"] == "angle":  # the chosen level with each count of candidates proposed per grid point
        specs += [(lod.setting(setting), lod.face_budget, args.grid, shader,
                   {"proposed": n, **({"photographed": True} if lod.photographed else {}), **dec, **per_point})
                  for n in args.proposed for shader in args.shader]
    rounds: list[list[dict]] = [[] for _ in specs]  # each row's timings, round after round over every row: the
    for i in range(args.rounds):  # machine's drift over minutes falls on every row alike
        for spec, kept in zip(specs, rounds, strict=True):
            kept.append(measure_budget(model, mesh, scene, *spec[:2], spec[2], side, args, spec[3], score=i == 0,
                                       photographed=spec[4].get("photographed", False),
                                       proposed=spec[4].get("proposed"), decimator=spec[4].get("decimator", "fast")))
            print(name, f"round {i + 1}", {**kept[-1], **spec[4]}, flush=True)
    rows = []
    for spec, kept in zip(specs, rounds, strict=True):
        timings = {k: round(statistics.median(r[k] for r in kept), 2) for k in TIMINGS}
        rows.append(_rates({**kept[0], **timings, **spec[4], "loadavg_1min": max(r["loadavg_1min"] for r in kept),
                            "rounds_fps": [round(1000 / r["frame_ms"], 2) for r in kept]}))
    full = rows[0]
    for r in rows:
        r["psnr_loss_db"] = round(full["psnr"] - r["psnr"], 3)
        r["speedup"] = round(full["frame_ms"] / r["frame_ms"], 2)
    timed_size = [round(scene.width * side / max(scene.width, scene.height)), round(scene.height * side / max(scene.width, scene.height))]
    return {"scene": name, "path": str(path), "mesh": str(mesh_file), "resolution": timed_size,
            "scored_resolution": [scene.width, scene.height],
            "setting": setting, "record": records.get(name), "faces_full": int(len(mesh.faces)), "rows": rows,
            "lod": lod.record()}


def main(argv: list[str] | None = None) -> dict:
    from omnirecon.data.io import write_json
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.mesh.ibr import REALTIME_FACE_BUDGET, REALTIME_FRAME_GRID
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    p.add_argument("--budgets", nargs="+", type=int, default=list(BUDGETS), help="face budgets (0: the full mesh)")
    p.add_argument("--mesh", nargs="*", default=[], help="NAME=FILE: a scene's mesh (input frame) instead of building it")
    p.add_argument("--grid", type=int, default=None, help="frame_grid of the budget rows (default REALTIME_FRAME_GRID)")
    p.add_argument("--shader", nargs="+", default=["auto"], choices=["auto", "torch"], help="the budget rows' "
                   "frame shaders, a row each (MeshRenderOptions.shader; the reference row: torch)")
    p.add_argument("--record", nargs="*", default=[], metavar="NAME=CURVE_JSON",
                   help="a scene's finetune record (curve.json of `omnirecon finetune --mesh` on that mesh): its "
                        "blend is timed and scored, as reconstruct draws it (default: the scene kind's defaults)")
    p.add_argument("--proposed", nargs="*", type=int, default=[], help="angle blend: rows at the chosen level with "
                   "this many candidate sources proposed per grid point beyond its own (GLBlend.PROPOSED), a row each")
    p.add_argument("--threads", type=int, default=2, help="shading workers and llvmpipe threads")
    p.add_argument("--frames", type=int, default=10, help="timed frames (median)")
    p.add_argument("--rounds", type=int, default=3, help="timing rounds over every row of a scene (each timing: the "
                   "median of its rounds)")
    p.add_argument("--max-views", type=int, default=8, help="held-out views scored")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "mesh_lod.json")
    a = p.parse_args(argv)
    a.grid = REALTIME_FRAME_GRID if a.grid is None else a.grid
    os.environ["LP_NUM_THREADS"] = str(a.threads)  # before the first GL context
    model, _ = load_checkpoint(ROOT / "checkpoints" / "omnirecon-tiny")
    commit = provenance(seed=0)["commit"]
    old = {}
    if a.out.is_file():
        old = {s["scene"]: s for s in json.loads(a.out.read_text()).get("scenes", [])}
    for name in a.scenes:
        row = run_scene(name, model, a)
        if row is not None:
            old[name] = {**row, "commit": commit, "loadavg_1min_end": round(os.getloadavg()[0], 2)}  # rows of other runs stay
    result = {"provenance": provenance(seed=0), "threads": a.threads, "frames": a.frames, "rounds": a.rounds,
              "realtime_face_budget": REALTIME_FACE_BUDGET, "realtime_frame_grid": REALTIME_FRAME_GRID, "machine_note": "2 CPU cores shared with other jobs: "
              "wall-clock FPS fall with the load average recorded beside each; CPU ms per frame are less affected",
              "scenes": [old[n] for n in SCENES if n in old]}
    write_json(a.out, result)
    return result
