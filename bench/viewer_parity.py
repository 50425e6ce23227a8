"""The web viewer against the real-time mesh path: held-out views drawn by headless Chromium and by ``MeshRenderer``.

    python -m bench viewer_parity                          # dtu_scan37, fern and synth_900997
    python -m bench viewer_parity --scenes dtu_scan37 --views 2 --out /tmp/vp
    python -m bench viewer_parity --folders lund=outputs/lund   # an `omnirecon reconstruct --out outputs/lund`

Per scene, the mesh and the ``finetune`` record (``curve.json``) a ``python -m bench depth_sources`` row wrote (as
``python -m bench realtime_blend``; :data:`ROWS`: ``--rows "dtu_scan37:stereo+fill, nearest 6, all views, angle blend,
nearest fill, angle auto, 8 held-out" "fern:stereo+fill, nearest 6" "synth_900997:stereo+model, nearest 6"``), and the real-time setting of that record
(:func:`omnirecon.mesh.ibr.realtime_setting`, with today's crack fill, ``--cracks``, where the record is older than it,
and without ``--soften``'s blur at depth edges, which the viewer does not draw); or (``--folders NAME=DIR``) a folder
laid out as ``reconstruct`` writes it (``mesh.ply``, ``finetune/curve.json``), drawn and exported with the checkpoint
its finetune stage saved (``finetune/checkpoint``, the weights the user's viewer bundle holds) where it is there:

* the bundle ``omnirecon export`` writes for it (:func:`omnirecon.workflows.export.run_export` with the scene, the
  checkpoint, the mesh and, where export takes one, the finetune record), served by ``omnirecon view``'s server and
  drawn by headless Chromium (software WebGL2) at each held-out camera, at the scene's resolution, as the bundle
  starts (its own blend, fill, sources);
* :class:`omnirecon.mesh.ibr.MeshRenderer`'s frame of the same camera with the same setting (each frame from its own
  nearest training views, as ``realtime_blend``, the videos and finetune's scores).

Reported per scene: held-out PSNR against the photo of each (whole image; over the object masks where the scene has
them), the browser's PSNR against ``MeshRenderer``'s frame and the max / mean absolute difference between the two
(8-bit levels), the browser's milliseconds per frame (``omnirecon.benchmark``: wall clock in the page, a small orbit
around the first held-out camera at the scene's resolution, SwiftShader on the CPU; and the CPU milliseconds of the
browser's processes over those frames, less bent by other jobs on the machine) and ``MeshRenderer``'s CPU
milliseconds per frame (1 thread). Pictures (photo | MeshRenderer | browser | 4x difference, one row per held-out view, at most
4) go to ``bench/results/figures/viewer_parity_<scene>.png``, every frame to ``--frames``.

Size: the two renderers of one frame (the bundle in the browser, ``MeshRenderer``), the inputs they share (a
depth_sources row or a reconstruct folder, the record's setting, the export) and the gap ladder between them are one
measurement.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import time
import urllib.parse
from pathlib import Path

import numpy as np
import torch

from omnirecon.data.io import write_image, write_json

ROOT = Path(__file__).resolve().parents[1]
ROWS = {"dtu_scan37": "stereo_fill_nearest_6_all_views_angle_blend_nearest_fill_angle_auto_8_held-out",
        "fern": "stereo_fill_nearest_6", "synth_900997": "stereo_model_nearest_6"}
"""The depth_sources row (its folder under outputs/bench/depth_sources) whose mesh and finetune record each scene uses:
dtu_scan37's default scoring (angle blend over every training view, source masks, nearest fill) on all 8 held-out
views; fern's (network blend of each frame's 6 nearest sources by distance, the far layer on the bounds box); a
procedural scene's stereo+model mesh, which has cracks (network blend of 6 sources per frame by angle, background)."""


REDRAW = ("(() => { omnirecon.render(); const gl = omnirecon.viewer.renderer.getContext();"
          " gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4)); return 1; })()")
"""The screenshot's redraw: draw the frame again and wait for it (a software frame can take seconds: redraws that do not
wait pile up faster than the GPU process draws them)."""


def session_cpu_seconds(sid: int) -> float:
    """CPU seconds (user + system) of every process in session ``sid`` so far: a headless Chromium and its helpers
    (its GPU process runs SwiftShader), from ``/proc`` (0 where there is none)."""
    total = 0
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            stat = (p / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()  # after the command name: state, ppid, pgrp, session, ...
        if int(fields[3]) == sid:
            total += int(fields[11]) + int(fields[12])  # utime, stime (clock ticks)
    return total / os.sysconf("SC_CLK_TCK")


def to_uint8(rgb) -> np.ndarray:
    """``# [H, W, 3]`` float in [0, 1] -> uint8, rounded as the videos (``render_frames``) and the canvas."""
    return (np.clip(np.asarray(rgb, dtype=np.float64), 0, 1) * 255 + 0.5).astype(np.uint8)


def psnr8(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB of two uint8 images ``# [H, W, 3]`` (over ``mask # [H, W]`` when given)."""
    d = (a.astype(np.float64) - b.astype(np.float64)) / 255
    se = (d * d).mean(-1)
    mse = float(se[mask].mean() if mask is not None else se.mean())
    return float(-10 * np.log10(max(mse, 1e-12)))


def python_frames(model, mesh, scene, targets: list[int], pool: list[int], setting: dict,
                  encoding: str | None = None, scale: float = 1.0) -> tuple[list, list[float]]:
    """``MeshRenderer``'s frames (uint8) of the held-out views under ``setting`` and the CPU ms of each (``encoding``:
    each frame's sources taken from :func:`shared_encoding` instead of encoded as a set; ``scale``: the cameras'
    resolution factor)."""
    from omnirecon.engine.views import select_sources
    from omnirecon.mesh.frames import ViewCache
    from omnirecon.mesh.ibr import realtime_options

    bg = tuple(scene.background) if scene.background is not None else (1.0, 1.0, 1.0)
    frames, ms = [], []
    with ViewCache(model, mesh, scene, realtime_options(setting, background=bg, visibility=True)) as cache:
        if encoding:
            cache._features.update(shared_encoding(model, scene, pool, targets, setting["sources"], encoding))
        for t in targets:
            cam = scene.cameras[t].to(dtype=torch.float32).rescaled(scale)
            picks = sorted(select_sources(scene, cam, pool, setting["sources"] or len(pool)))
            with cache.renderer(picks) as r:
                r.render(cam, extras=False)  # warm-up
                c0 = time.process_time()
                rgb = r.render(cam, extras=False)["rgb"]
                ms.append(1000 * (time.process_time() - c0))
            frames.append(to_uint8(rgb.float().cpu().numpy()))
    return frames, ms


def shared_encoding(model, scene, pool: list[int], targets: list[int], k: int, how: str) -> dict:
    """Per target, the features of its ``k`` nearest sources taken from one encoding of more views than that set (what a
    bundle of fixed features can hold): ``how`` ``"pool"``, every view of ``pool`` encoded together; ``"own"``, each
    view encoded with its own ``k - 1`` nearest views of the pool. ``{tuple(set): OmniReconFeatures}``"""
    from dataclasses import replace

    from omnirecon.engine.views import select_sources
    from omnirecon.rays import Sources

    with torch.inference_mode():
        if how == "pool":
            maps = model.encode_appearance(Sources.from_scene(scene, pool)).maps  # [P, C, h, w]
        else:
            maps = torch.cat([model.encode_appearance(Sources.from_scene(scene, [v, *[u for u in select_sources(
                scene, scene.cameras[v], pool, k) if u != v][:k - 1]])).maps[:1] for v in pool])
        full = model.encode_appearance(Sources.from_scene(scene, pool[:1]))
        out = {}
        for t in targets:
            picks = sorted(select_sources(scene, scene.cameras[t].to(dtype=torch.float32), pool, k))
            out[tuple(picks)] = replace(full, sources=Sources.from_scene(scene, picks),
                                        maps=maps[[pool.index(v) for v in picks]])
    return out


def gap_ladder(model, mesh, scene, targets: list[int], pool: list[int], setting: dict, old_views: list[int]) -> list:
    """``MeshRenderer``'s held-out PSNR from what main's viewer drew (``old_views``, the far fill or the background
    colour, no source masks, no cracks) up to ``setting``, one gap closed per rung."""
    old = {**setting, "fill": "background" if setting["fill"] == "background" else "far", "source_masks": False,
           "cracks": 0}
    if setting["blend"] == "angle":
        rungs = [("every training view", {"sources": 0}), ("source masks", {"source_masks": setting["source_masks"]}),
                 ("nearest fill", {"fill": setting["fill"]}), ("cracks", {"cracks": setting["cracks"]})]
    else:
        rungs = [(f"{setting['sources']} nearest per frame, one pool encoding", {"sources": setting["sources"],
                                                                                 "encoding": "pool"}),
                 (f"{setting['sources']} nearest per frame, each view with its nearest", {"encoding": "own"}),
                 (f"{setting['sources']} nearest per frame, each set encoded", {"encoding": None}),
                 ("fill", {"fill": setting["fill"]}), ("cracks", {"cracks": setting["cracks"]})]
    out, current = [], {**old, "encoding": None}
    for name, change in [("main's viewer", {}), *rungs]:
        current = {**current, **change}
        frames, _ = python_frames(model, mesh, scene, targets, old_views if name == "main's viewer" else pool, current,
                                  current.get("encoding"))
        row = {"rung": name, "setting": dict(current)}
        row["psnr"] = float(np.mean([psnr8(f, to_uint8(scene.images[t].float().numpy())) for t, f in zip(targets, frames)]))
        if scene.masks is not None:
            row["psnr_masked"] = float(np.mean([psnr8(f, to_uint8(scene.images[t].float().numpy()),
                                                      scene.masks[t].bool().numpy()) for t, f in zip(targets, frames)]))
        print(f"  {name}: {row['psnr']:.2f} dB" + (f", masks {row['psnr_masked']:.2f}" if "psnr_masked" in row else ""),
              flush=True)
        out.append(row)
    return out


def input_camera(scene, t: int, scale: float = 1.0) -> dict:
    """Held-out camera ``t`` (its resolution times ``scale``) as the viewer takes it: OpenCV intrinsics and
    camera-to-world in the input frame."""
    cam = scene.cameras[t].to(dtype=torch.float32).rescaled(scale).to(dtype=torch.float64).transformed(scene.to_input)
    return {"fx": float(cam.fx[0]), "fy": float(cam.fy[0]), "cx": float(cam.cx[0]), "cy": float(cam.cy[0]),
            "width": cam.width, "height": cam.height, "c2w": cam.c2w[0].tolist(), "frame": "input"}


def browser_frames(bundle: Path, cameras: list[dict], bench_frames: int, timeout: float,
                   toggles: tuple[tuple[str, str], ...] = ()) -> tuple[list, dict, dict, dict]:
    """Headless Chromium's screenshots (uint8) of ``cameras`` drawn by the bundle as it starts, ``omnirecon.info``,
    ``omnirecon.benchmark(bench_frames)`` at the first camera, and ``{name: screenshots}`` after each of ``toggles``
    (``(name, JavaScript)``, applied one after the other: each turns one more part of the setting off)."""
    from PIL import Image

    from omnirecon.viewer.headless import HeadlessChromium
    from omnirecon.viewer.server import ViewerServer

    W, H = cameras[0]["width"], cameras[0]["height"]
    server = ViewerServer(bundle, port=0, quiet=True)
    server.start()
    off = {}
    try:
        with HeadlessChromium(W, H, timeout=timeout) as browser:
            query = urllib.parse.urlencode({"camera": json.dumps(cameras[0])})
            browser.goto(server.url + "index.html?" + query)
            state = browser.wait_for("document.documentElement.dataset.state !== 'loading' && "
                                     "document.documentElement.dataset.state")
            if state != "ready":
                raise RuntimeError(f"viewer: {browser.evaluate('document.documentElement.dataset.error')}; "
                                   f"{browser.console()[-5:]}")
            info = browser.evaluate("omnirecon.info")

            def shoot() -> list[np.ndarray]:
                shots = []
                for cam in cameras:
                    browser.evaluate(f"omnirecon.setCamera({json.dumps(cam)}), 1", timeout=timeout)
                    png = browser.screenshot(None, W, H, redraw=REDRAW)
                    shots.append(np.asarray(Image.open(io.BytesIO(png)).convert("RGB")))
                return shots

            shots = shoot()
            browser.evaluate(f"omnirecon.setCamera({json.dumps(cameras[0])}), 1", timeout=timeout)
            browser.evaluate("omnirecon.benchmark(1)", timeout=timeout)  # warm-up
            cpu = session_cpu_seconds(browser.proc.pid)
            speed = browser.evaluate(f"omnirecon.benchmark({bench_frames})", timeout=timeout)
            speed["cpu_ms_per_frame"] = 1000 * (session_cpu_seconds(browser.proc.pid) - cpu) / bench_frames
            for name, js in toggles:
                browser.evaluate(f"{js}, 1", timeout=timeout)
                off[name] = shoot()
    finally:
        server.stop()
    return shots, info, speed, off


def toggles_of(setting: dict) -> tuple[tuple[str, str], ...]:
    """The parts of ``setting`` the viewer can turn off, cumulatively: source masks, the nearest fill (to the far
    layer), the crack fill."""
    out = []
    if setting["blend"] == "angle" and setting["source_masks"]:
        out.append(("source masks", "omnirecon.setMasks(false)"))
    if setting["fill"] == "nearest":
        out.append(("nearest fill", "omnirecon.setFill('far')"))
    if setting.get("cracks"):
        out.append(("cracks", "omnirecon.setCracks(false)"))
    return tuple(out)


def export_bundle(scene_path: Path, resolution: int, mesh_file: Path, record_folder: Path, setting: dict,
                  out: Path, ckpt: Path) -> dict:
    """``omnirecon export`` of the mesh as a user runs it after ``finetune`` (the record's folder where export takes
    it; else the setting's blend and angle sources, which export took before)."""
    from dataclasses import fields

    from omnirecon.workflows.export import ExportConfig, run_export

    names = {f.name for f in fields(ExportConfig)}
    extra = {"finetune": record_folder} if "finetune" in names else {"blend": setting["blend"],
                                                                     "angle_sources": setting["angle_sources"]}
    cfg = ExportConfig(scene=scene_path, ckpt=ckpt, mesh=mesh_file, out=out,
                       resolution=resolution, threads=1, **extra)
    return run_export(cfg)


FIGURE_VIEWS = 4
"""Views in a scene's figure at most (evenly spaced; every frame is in ``--frames``)."""


def figure(rows: list[list[np.ndarray]], path: Path) -> None:
    """One row per view (at most :data:`FIGURE_VIEWS`): photo | MeshRenderer | browser | 4x |browser - MeshRenderer|,
    2-px white gaps (frames under 200 px drawn at twice their size)."""
    lines = []
    for photo, ref, shot in rows[::-(-len(rows) // FIGURE_VIEWS)]:
        diff = np.clip(np.abs(shot.astype(np.int16) - ref.astype(np.int16)) * 4, 0, 255).astype(np.uint8)
        if max(photo.shape[:2]) < 200:
            photo, ref, shot, diff = (np.repeat(np.repeat(a, 2, 0), 2, 1) for a in (photo, ref, shot, diff))
        gap = np.full((photo.shape[0], 2, 3), 255, np.uint8)
        lines.append(np.concatenate([photo, gap, ref, gap, shot, gap, diff], 1))
        lines.append(np.full((2, lines[-1].shape[1], 3), 255, np.uint8))
    write_image(path, np.concatenate(lines[:-1], 0))


def tuned_checkpoint(folder: Path) -> Path | None:
    """The checkpoint ``finetune --save`` left in ``folder/finetune`` (``reconstruct`` saves one), or None."""
    ckpt = folder / "finetune" / "checkpoint"
    return ckpt if (ckpt / "meta.json").is_file() else None


def run_scene(name: str, folder: Path, cracks: int | None, views: int | None, frames_dir: Path, results: Path,
              bench_frames: int, timeout: float, gaps: bool = False) -> dict:
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.engine.scenes import load_at_resolution
    from omnirecon.mesh.files import read_mesh
    from omnirecon.mesh.ibr import realtime_setting

    record = json.loads((folder / "finetune" / "curve.json").read_text())
    side = max(record["resolution"])
    scene_path = Path(record["scene"])
    if not scene_path.is_absolute() and (folder / scene_path).is_dir():  # reconstruct's record: relative to its folder
        scene_path = folder / scene_path
    scene = load_at_resolution(scene_path, side, "white")
    render = dict(record.get("render") or {})
    if cracks is not None and "cracks" not in render:
        render["cracks"] = cracks  # a record from before the crack fill: today's default
    render["soften"] = 0.0  # the viewer does not blur depth edges (finetune --soften): compare like with like
    setting = realtime_setting(scene, {**record, "render": render})
    mesh = read_mesh(folder / "mesh.ply", scene.to_input)
    ckpt = tuned_checkpoint(folder) or ROOT / "checkpoints" / "omnirecon-tiny"
    model, _ = load_checkpoint(ckpt)
    targets, pool = record["held_out"][:views], record["sources"]
    if gaps:
        from omnirecon.engine.views import default_views

        return {"scene": name, "held_out": targets, "gaps": gap_ladder(model, mesh, scene, targets, pool, setting,
                                                                       default_views(scene, 3))}
    if render != record.get("render"):
        record = {**record, "render": render}
        (frames_dir / "finetune").mkdir(parents=True, exist_ok=True)
        write_json(frames_dir / "finetune" / "curve.json", record)  # what export reads: the record with the cracks
        record_folder = frames_dir / "finetune"
    else:
        record_folder = folder / "finetune"
    start = time.process_time()
    exported = export_bundle(scene_path, side, folder / "mesh.ply", record_folder, setting,
                             frames_dir / "export", ckpt)
    export_s = time.process_time() - start
    bundle = Path(exported["out"]) / "viewer"
    meta = json.loads((bundle / "bundle.json").read_text())
    refs, py_ms = python_frames(model, mesh, scene, targets, pool, setting)
    shots, info, speed, off = browser_frames(bundle, [input_camera(scene, t) for t in targets], bench_frames, timeout,
                                             toggles_of(setting) if meta.get("version", 1) >= 2 else ())
    per_view, pics = [], []
    for t, ref, shot in zip(targets, refs, shots):
        photo = to_uint8(scene.images[t].float().numpy())
        mask = scene.masks[t].bool().numpy() if scene.masks is not None else None
        d = np.abs(shot.astype(np.int16) - ref.astype(np.int16))
        v = {"view": t, "browser": psnr8(shot, photo), "python": psnr8(ref, photo), "parity": psnr8(shot, ref),
             "max_diff": int(d.max()), "mean_diff": float(d.mean()), "over_8": float((d.max(-1) > 8).mean())}
        if mask is not None:
            v.update(browser_masked=psnr8(shot, photo, mask), python_masked=psnr8(ref, photo, mask),
                     parity_masked=psnr8(shot, ref, mask))
        per_view.append(v)
        for kind, img in (("photo", photo), ("python", ref), ("browser", shot)):
            write_image(frames_dir / f"view{t:02d}_{kind}.png", img)
        pics.append([photo, ref, shot])
    figure(pics, results / "figures" / f"viewer_parity_{name}.png")
    mean = lambda k: float(np.mean([v[k] for v in per_view]))  # noqa: E731
    row = {"scene": name, "mesh_file": str((folder / "mesh.ply").relative_to(ROOT)) if folder.is_relative_to(ROOT)
           else str(folder / "mesh.ply"), "held_out": targets, "resolution": record["resolution"], "setting": setting,
           "bundle": {k: meta.get(k) for k in ("version", "blend", "fill", "visibility")} | {
               "sources": meta["sources"]["count"], "faces": meta["faces"],
               "megabytes": round(sum(f.stat().st_size for f in bundle.rglob("*") if f.is_file()) / 1e6, 1)},
           "viewer": info, "export_cpu_s": export_s, "tuned": tuned_checkpoint(folder) is not None,
           "checkpoint": str(ckpt.relative_to(ROOT)) if ckpt.is_relative_to(ROOT) else str(ckpt),
           "browser": mean("browser"), "python": mean("python"), "parity": mean("parity"),
           "max_diff": max(v["max_diff"] for v in per_view), "mean_diff": mean("mean_diff"), "over_8": mean("over_8"),
           "browser_ms_per_frame": speed["ms_per_frame"], "browser_cpu_ms_per_frame": speed["cpu_ms_per_frame"],
           "browser_frames": speed["frames"],
           "python_cpu_ms_per_frame": float(np.median(py_ms)), "per_view": per_view,
           "scored_by": "objects" if record.get("scored_by") == "objects" and scene.masks is not None else "image"}
    if scene.masks is not None:
        row.update(browser_masked=mean("browser_masked"), python_masked=mean("python_masked"),
                   parity_masked=mean("parity_masked"))
    row["browser_off"] = []  # the browser's PSNR with each part of the setting turned off, cumulatively
    for name, frames in off.items():
        photos = [to_uint8(scene.images[t].float().numpy()) for t in targets]
        r = {"off": name, "psnr": float(np.mean([psnr8(f, p) for f, p in zip(frames, photos)]))}
        if scene.masks is not None:
            r["psnr_masked"] = float(np.mean([psnr8(f, p, scene.masks[t].bool().numpy())
                                              for f, p, t in zip(frames, photos, targets)]))
        row["browser_off"].append(r)
    return row


def main(argv: list[str] | None = None) -> dict:
    from bench.depth_rows import row_arguments
    from omnirecon.mesh.fill import CRACK_RADIUS
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    row_arguments(p, ROWS)
    p.add_argument("--folders", nargs="*", default=[], metavar="NAME=DIR",
                   help="also (without --scenes: only) these folders, each with mesh.ply and finetune/curve.json (an "
                        "`omnirecon reconstruct --out DIR`; its tuned finetune/checkpoint draws and exports where it is "
                        "there), a row each named NAME")
    p.add_argument("--cracks", type=int, default=CRACK_RADIUS,
                   help="crack radius where the finetune record predates the crack fill (0: as it scored)")
    p.add_argument("--views", type=int, default=None, help="only the first N held-out views")
    p.add_argument("--bench-frames", type=int, default=5, help="frames of the browser's timing")
    p.add_argument("--timeout", type=float, default=600.0, help="seconds the browser may take per step")
    p.add_argument("--frames", type=Path, default=ROOT / "outputs" / "bench" / "viewer_parity",
                   help="where the bundles and every frame go")
    p.add_argument("--gaps", action="store_true",
                   help="no browser: MeshRenderer from main's viewer's setting to the real-time one, a gap at a time "
                        "(written to viewer_parity_gaps.json)")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    a.scenes_given = "--scenes" in (sys.argv[1:] if argv is None else argv)
    torch.set_num_threads(1)
    out_file = a.out / ("viewer_parity_gaps.json" if a.gaps else "viewer_parity.json")
    old = json.loads(out_file.read_text()) if out_file.is_file() else {}
    folders = dict(f.split("=", 1) for f in a.folders)
    scenes = [n for n in a.scenes if n not in folders] if a.scenes_given or not folders else []
    jobs = [(n, a.meshes / f"{n}_{ROWS[n]}") for n in scenes] + [(n, Path(d).resolve()) for n, d in folders.items()]
    here = provenance(seed=0)
    kept = [{"commit": old["provenance"]["commit"], **r} for r in old.get("rows", [])
            if r["scene"] not in dict(jobs)]  # each row keeps the commit it ran at
    result = {"provenance": here, "rows": kept}
    for name, folder in jobs:
        row = run_scene(name, folder, a.cracks, a.views, a.frames / name, a.out, a.bench_frames, a.timeout, a.gaps)
        row["load_average"] = list(os.getloadavg())
        row["commit"] = here["commit"]
        result["rows"].append(row)
        if a.gaps:
            write_json(out_file, result)
            continue
        key = "_masked" if row["scored_by"] == "objects" else ""
        print(f"{name}: PSNR{' (masks)' if key else ''} browser {row['browser' + key]:.2f}, MeshRenderer "
              f"{row['python' + key]:.2f}; browser vs MeshRenderer {row['parity']:.2f} dB (max diff {row['max_diff']}, "
              f"mean {row['mean_diff']:.2f} levels); browser {row['browser_ms_per_frame']:.0f} ms "
              f"({row['browser_cpu_ms_per_frame']:.0f} CPU-ms) per frame, "
              f"MeshRenderer {row['python_cpu_ms_per_frame']:.0f} CPU-ms; bundle {row['bundle']}", flush=True)
        for r in row["browser_off"]:
            print(f"  browser without {r['off']} too: {r['psnr' + key]:.2f} dB", flush=True)
        write_json(out_file, result)
    return result
