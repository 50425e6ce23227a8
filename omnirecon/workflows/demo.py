"""``omnirecon demo``: from posed images to novel views, a mesh and measured numbers, in one command.

With the shipped checkpoints (:func:`omnirecon.engine.shipped.shipped_checkpoint`) and no per-scene training, the demo

1. builds the embedded default scene (procedural, seed :data:`DEMO_SEED`, a held-out seed) or reads
   ``--data PATH`` (any supported format), and draws its cameras;
2. renders a novel-view orbit (MP4, or GIF without ffmpeg) with GPNR and with Omni-Recon;
3. scores held-out views of the scene for the plane-sweep floor and every shipped model;
4. extracts Omni-Recon's mesh (IBRNet's density mesh when only ibrnet-tiny ships) and, on procedural
   scenes, prints its Chamfer distance to the exact ground-truth mesh;
5. writes ``<out>/index.html`` with every picture, video and table, and ``demo.json`` with the numbers.

Every stage shows a progress bar; ``--quick`` is a reduced mode (fewer frames and targets, lower
resolution) used by the tests.

Size: one workflow of five stages, each a short function that runs its verb and builds its report section;
they are here together because only the demo uses them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from omnirecon.engine.machine import GuidedRendering, ThreadsConfig
from omnirecon.engine.shipped import shipped_folder
from omnirecon.errors import InputError
from omnirecon.options import CameraPath, ImageSize, OutPath, QuickRun, SourceViews, command_defaults

DEMO_SEED = 900_999
"""Seed of the embedded demo scene: the last of the reserved evaluation seeds (never trained on,
and not among the first scenes of ``synth:eval``)."""
ORBIT_SECONDS = 2.0
"""Length of each novel-view orbit's video in seconds (its frame rate: ``--frames`` over this), about as long as the
mesh path's orbit video."""
RENDER_MODELS = ("gpnr-tiny", "omnirecon-tiny")
"""Shipped checkpoints whose novel-view orbit the demo renders, each with its checkpoint's render options
(gpnr-tiny: 24 samples in bf16; omnirecon-tiny: the coarse pass; each several times faster than the full render
and as good on held-out views: ``python -m bench tiny_levers``, BENCHMARKS "Render levers of the tiny presets")."""
SCORE_MODELS = ("floor", "gpnr-tiny", "ibrnet-tiny", "omnirecon-tiny")
"""Models scored on the held-out views (the floor needs no checkpoint), each with its checkpoint's render options."""
MESH_MODELS = ("omnirecon-tiny", "ibrnet-tiny")
"""Models the demo may mesh, in order: it meshes the first shipped one only. With stereo depth first (``mesh
--depth auto``) the two models' meshes were identical wherever stereo matched, and the second all-view mesh cost
99-173 s of the demo; ``omnirecon mesh --ckpt checkpoints/ibrnet-tiny`` and BENCHMARKS' geometry tables compare
them."""


@dataclass
@command_defaults(out=Path("outputs/demo"), frames=6, resolution=256)
class DemoConfig(GuidedRendering, OutPath, SourceViews, ImageSize, CameraPath, QuickRun, ThreadsConfig):
    """Run the whole pipeline on one scene with the shipped checkpoints and write an HTML report:
    novel-view videos (GPNR, Omni-Recon), held-out view scores against the non-learned floor, and a
    mesh with its Chamfer distance to the ground truth."""

    data: Path | None = None
    """Any supported scene folder instead of the embedded procedural scene."""
    checkpoints: Path = shipped_folder()
    """Folder of the checkpoints the demo runs, one sub-folder per preset (default: the shipped ones, which the
    package carries: omnirecon/engine/shipped.py)."""
    orbit_guided: bool = True
    """Render the novel-view orbits surface-guided with each model family's default layout even without
    ``--guided.on`` (fewer samples per ray at the orbits' size; ``--guided.on`` sets the options instead;
    ``--no-orbit-guided``: every ray on the model's full path)."""
def _checkpoint(cfg: DemoConfig, name: str) -> Path | None:
    path = Path(cfg.checkpoints) / name
    return path if (path / "model.safetensors").is_file() else None


def demo_scene(cfg: DemoConfig, resolution: int | None = None) -> Path:
    """The scene folder: ``--data`` (checked) or the embedded procedural scene (generated into ``<out>/scene``, at
    ``resolution`` px: ``<out>/scene_<resolution>``; default 128, quick 64)."""
    from omnirecon.data import detect_format  # lazy: demo --help stays fast
    from omnirecon.data.synth.generate import SynthOptions, generate_scene  # lazy: demo --help stays fast

    if cfg.data is not None:
        detect_format(Path(cfg.data))  # one-line error for a missing or unsupported folder
        return Path(cfg.data)
    default = 64 if cfg.quick else 128
    res = resolution if resolution is not None and resolution > default else default
    folder = Path(cfg.out) / ("scene" if res == default else f"scene_{res}")
    return generate_scene(folder, DEMO_SEED, SynthOptions(rig="object", views=24, resolution=res))


def run_demo(cfg: DemoConfig) -> dict:
    """Run the demo; returns ``{"report", "lines", "numbers"}`` (numbers are also in ``demo.json``)."""
    from omnirecon.engine.machine import set_threads  # lazy: demo --help stays fast
    from omnirecon.options import check_options  # lazy: demo --help stays fast

    check_options("demo", cfg)  # the numbers (omnirecon/options.py); here for callers other than the CLI
    set_threads(cfg.threads)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    numbers: dict = {"seconds": {}}
    lines: list[str] = []
    start_all = time.perf_counter()
    path, scene, section = scene_section(cfg, out, numbers, lines)
    sections = [section, orbits_section(cfg, path, out, numbers, lines), scores_section(cfg, path, out, numbers, lines),
                meshes_section(cfg, path, out, numbers, lines), *model_sections(cfg, path, scene, out, numbers, lines)]
    report = finish(out, sections, numbers, lines, start_all)
    return {"report": str(report), "lines": lines, "numbers": numbers}


def clocks() -> tuple[float, float]:
    """Wall and process CPU seconds now (every thread of the process counts in the CPU clock)."""
    return time.perf_counter(), time.process_time()


def lap(numbers: dict, key: str, start: tuple[float, float]) -> None:
    """The stage ``key`` started at ``start`` (:func:`clocks`): wall seconds into ``numbers["seconds"]``, CPU
    seconds into ``numbers["cpu_seconds"]`` (with 2 threads a stage may cost more CPU than wall)."""
    wall, cpu = clocks()
    numbers["seconds"][key] = wall - start[0]
    numbers.setdefault("cpu_seconds", {})[key] = round(cpu - start[1], 2)


def timed(numbers: dict, key: str, fn, *args):
    """``fn(*args)``, its wall and CPU seconds stored under ``key`` (:func:`lap`)."""
    t = clocks()
    value = fn(*args)
    lap(numbers, key, t)
    return value


def scene_section(cfg: DemoConfig, out: Path, numbers: dict, lines: list[str]):
    """Stage 1: the scene and its cameras; returns ``(path, scene, section)``."""
    from omnirecon.data import load_scene  # lazy: demo --help stays fast
    from omnirecon.engine.report import Section  # lazy: demo --help stays fast
    from omnirecon.workflows.inspect import draw_cameras  # lazy: demo --help stays fast

    t = clocks()
    path = demo_scene(cfg)
    scene = load_scene(path)
    if len(scene) < cfg.num_views + 1:
        raise InputError(f"the scene has {len(scene)} views; the demo needs more than --num-views {cfg.num_views}",
                         path, "pass a scene with more views or a smaller --num-views")
    draw_cameras(scene, out / "cameras.png")
    numbers["scene"] = {"path": str(path), "views": len(scene), "size": [scene.width, scene.height],
                        "format": scene.format, "seed": DEMO_SEED if cfg.data is None else None}
    lap(numbers, "scene", t)
    what = f"procedural scene, seed {DEMO_SEED} (held out from training)" if cfg.data is None else str(path)
    lines.append(f"scene: {what}, {len(scene)} views")
    return path, scene, (Section("Scene").text(f"{what}: {len(scene)} views at {scene.width}x{scene.height}, "
                                               f"format {scene.format}.")
                         .figure(out / "cameras.png", out, "cameras (frustums by split) and the scene bounds", 480))


def orbits_section(cfg: DemoConfig, path: Path, out: Path, numbers: dict, lines: list[str]):
    """Stage 2: a novel-view orbit per model of :data:`RENDER_MODELS`."""
    from omnirecon.engine.report import Section  # lazy: demo --help stays fast
    from omnirecon.models.guided import GuidedOptions  # lazy: demo --help stays fast
    from omnirecon.workflows.render import RenderConfig, run_render  # lazy: demo --help stays fast

    frames, res = (4, 48) if cfg.quick else (cfg.frames, cfg.resolution)
    path = demo_scene(cfg, res)  # the embedded scene at the frames' size (sources are never upscaled)
    guided = cfg.guided if cfg.guided.on or not cfg.orbit_guided else GuidedOptions(on=True)
    videos = Section("Novel views").text(
        f"An orbit of {frames} frames at a {res}-px long side, each frame rendered from its {cfg.num_views} "
        "nearest source views, with no per-scene training" + (", surface-guided (samples around the model's own "
                                                              "low-resolution depth)." if guided.on else "."))
    for name in RENDER_MODELS:
        ckpt = _checkpoint(cfg, name)
        if ckpt is None:
            videos.text(f"{name}: no shipped checkpoint in {cfg.checkpoints}; skipped.", "note")
            continue
        render = RenderConfig(scene=path, ckpt=ckpt, path="orbit", frames=frames, resolution=res,
                              num_views=cfg.num_views, out=out / f"orbit_{name}", guided=guided,
                              fps=max(1, round(frames / ORBIT_SECONDS)))
        folder, video = timed(numbers, f"orbit_{name}", run_render, render)
        videos.figure(video, out, f"{name}: {frames} frames, {numbers['seconds'][f'orbit_{name}']:.0f} s", 320)
        lines.append(f"orbit {name}: {video}")
    return videos


def score_model(cfg: DemoConfig, path: Path, out: Path, name: str) -> tuple[dict, dict] | None:
    """``(scene result, setting)`` of ``omnirecon eval`` for one model at K = --num-views (None: no checkpoint
    or no such setting)."""
    from omnirecon.engine.evaluate import evaluate  # lazy: demo --help stays fast
    from omnirecon.engine.machine import load_model  # lazy: demo --help stays fast
    from omnirecon.engine.protocols import set_long_side

    ckpt = _checkpoint(cfg, name) if name != "floor" else None
    if name != "floor" and ckpt is None:
        return None
    net, info = load_model(ckpt, "floor" if name == "floor" else None, long_side=set_long_side("cpu"))
    r = evaluate(net, [path], (cfg.num_views,), out / f"eval_{name}", model_info=info, protocol_set="cpu",
                 max_targets=1 if cfg.quick else None, progress=True, guided=cfg.guided)
    scene_r = r["scenes"][0]
    setting = scene_r["settings"].get(str(cfg.num_views))
    return None if setting is None else (scene_r, setting)


def scores_section(cfg: DemoConfig, path: Path, out: Path, numbers: dict, lines: list[str]):
    """Stage 3: held-out view scores of :data:`SCORE_MODELS`, with one panel each."""
    from omnirecon.engine.report import Section  # lazy: demo --help stays fast

    t = clocks()
    rows, panels = [], []
    for name in SCORE_MODELS:
        scored = score_model(cfg, path, out, name)
        if scored is None:
            continue
        scene_r, setting = scored
        m = setting["mean"]
        rows.append([name, m.get("psnr", float("nan")), m.get("ssim", float("nan")),
                     m.get("st_lpips_alex", float("nan")), m.get("depth_abs_rel", float("nan")),
                     setting["seconds_per_view"]])
        numbers.setdefault("scores", {})[name] = m
        first = setting["views"][0]
        panel = out / f"eval_{name}" / scene_r["name"] / f"k{cfg.num_views}"
        found = sorted(panel.glob(f"{first['index']:03d}_*.png"))
        if found:
            panels.append((found[0], f"{name}: GT | render | error, view {first['index']}"))
    lap(numbers, "scores", t)
    scores = Section("Held-out views").text(
        f"Targets and sources by the `cpu` protocol set of `omnirecon eval` (64-px long side), K = {cfg.num_views}. "
        "The floor is the non-learned plane sweep every learned model must beat.")
    scores.table(["model", "PSNR", "SSIM", "ST-LPIPS", "depth abs rel", "s / view"], rows)
    for p, caption in panels:
        scores.figure(p, out, caption, 300)
    for r in rows:
        lines.append(f"held-out views {r[0]}: PSNR {r[1]:.2f} dB, SSIM {r[2]:.3f}")
    return scores


def mesh_numbers(rec: dict) -> dict:
    """The demo's numbers of one ``omnirecon mesh`` record."""
    met = rec.get("metrics", {})
    ch = met.get("chamfer", {})
    return {"faces": rec["faces"].get("final", rec["faces"]["components"]), "chamfer": ch.get("chamfer"), "fscore": ch.get("fscore"),
            "chamfer_rel": met.get("chamfer_rel"), "mask_iou": met.get("mask_iou", {}).get("mean"),
            "seconds": rec["seconds"]["images_to_mesh"]}


def meshes_section(cfg: DemoConfig, path: Path, out: Path, numbers: dict, lines: list[str]):
    """Stage 4: a mesh per model of :data:`MESH_MODELS` (``mesh_<model>.ply`` / ``.glb``) and its scores."""
    from omnirecon.engine.report import Section  # lazy: demo --help stays fast
    from omnirecon.workflows.mesh import MeshConfig, run_mesh, summary_lines  # lazy: demo --help stays fast

    meshes = Section("Mesh").text(
        "`omnirecon mesh --views all`: depth at every training view (`--depth auto`: classical stereo, and the "
        f"model's depth rendered from the {min(cfg.num_views, 3)} nearest views where stereo finds none), fused with "
        "confidence weights at a scale fitted to the depth maps, marching cubes, cleaning, a face budget; background "
        "kept; exported in the input frame (PLY and GLB). The mesh-path and fine-tuning sections below use this mesh; "
        "`omnirecon mesh --ckpt checkpoints/ibrnet-tiny` meshes the IBRNet-density baseline (identical wherever "
        "stereo matched, so the demo leaves it out).")
    mesh_rows = []
    for name in [m for m in MESH_MODELS if _checkpoint(cfg, m) is not None][:1]:
        ckpt = _checkpoint(cfg, name)
        mesh_cfg = MeshConfig(scene=path, ckpt=ckpt, views=("all",), num_views=min(cfg.num_views, 3),
                              out=(out / f"mesh_{name}.ply", out / f"mesh_{name}.glb"),
                              resolution=48 if cfg.quick else 128, voxel=1 / 96 if cfg.quick else None)
        rec = timed(numbers, f"mesh_{name}", run_mesh, mesh_cfg)
        nm = numbers.setdefault("mesh", {})[name] = mesh_numbers(rec)
        mesh_rows.append([name, nm["faces"], "–" if nm["chamfer"] is None else nm["chamfer"],
                          "–" if nm["chamfer_rel"] is None else f"{100 * nm['chamfer_rel']:.2f} %",
                          "–" if nm["fscore"] is None else nm["fscore"],
                          "–" if nm["mask_iou"] is None else nm["mask_iou"], nm["seconds"]])
        preview = out / f"mesh_{name}_preview.png"
        if preview.is_file():
            meshes.figure(preview, out, f"{name} mesh from source view {rec['views'][0]}", 320)
        meshes.link(out / f"mesh_{name}.glb", out, f"{name} mesh (GLB)")
        lines.extend(f"mesh {name}: {line}" for line in summary_lines(rec))
    if mesh_rows:
        meshes.table(["model", "faces", "Chamfer (input units)", "Chamfer / GT extent", "F-score",
                      "silhouette IoU", "images -> mesh (s)"], mesh_rows)
    return meshes


def model_sections(cfg: DemoConfig, path: Path, scene, out: Path, numbers: dict, lines: list[str]) -> list:
    """Stage 5: the real-time mesh path, fine-tuning and lifting (Omni-Recon; lifting also with IBRNet)."""
    sections = []
    omni = _checkpoint(cfg, "omnirecon-tiny")
    omni_mesh = out / "mesh_omnirecon-tiny.ply"
    if omni is not None and omni_mesh.is_file():
        for key, fn in (("mesh_path", mesh_path_section), ("finetune", finetune_section)):
            sections.append(timed(numbers, key, fn, cfg, path, omni, omni_mesh, out, numbers, lines))
    lifter = omni or _checkpoint(cfg, "ibrnet-tiny")
    if lifter is not None:
        sections.append(timed(numbers, "lift", lift_section, cfg, path, scene, lifter, out, numbers, lines))
    return sections


def finish(out: Path, sections: list, numbers: dict, lines: list[str], start_all: float) -> Path:
    """The overview strip, ``demo.json`` and ``index.html``; returns the report's path."""
    import torch  # lazy: demo --help stays fast

    from omnirecon.data.io import write_json  # lazy: demo --help stays fast
    from omnirecon.engine.report import Section, write_report  # lazy: demo --help stays fast
    from omnirecon.provenance import markdown_header, provenance  # lazy: demo --help stays fast

    overview = overview_figure(out)
    if overview is not None:
        sections.insert(0, Section("Overview").figure(overview, out, "one held-out scene: what the demo produced", 900))
    numbers["seconds"]["total"] = time.perf_counter() - start_all
    numbers["threads"] = torch.get_num_threads()
    numbers["provenance"] = provenance(seed=0)
    write_json(out / "demo.json", numbers)
    footer = (markdown_header(numbers["provenance"]).replace("`", "")
              + f". Total {numbers['seconds']['total']:.0f} s. Numbers: demo.json.")
    report = write_report(out, "omnirecon demo", sections, footer)
    lines.append("seconds per stage: " + ", ".join(f"{k} {v:.1f}" for k, v in numbers["seconds"].items()
                                                     if k != "total"))
    lines.append(f"total {numbers['seconds']['total']:.0f} s ({time.process_time():.0f} CPU-s, "
                 f"{numbers['threads']} torch threads)")
    return report


def mesh_path_section(cfg: DemoConfig, path: Path, ckpt: Path, mesh_file: Path, out: Path, numbers: dict,
                      lines: list[str]):
    """Render an orbit through the mesh with the appearance branch (source features cached) and time it."""
    import statistics

    import torch

    from omnirecon.data.io import write_image  # lazy: demo --help stays fast
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.engine.lod import choose_level_of_detail
    from omnirecon.engine.views import select_sources
    from omnirecon.mesh.ibr import realtime_setting
    from omnirecon.workflows.mesh import scene_frame_mesh
    from omnirecon.workflows.render import mesh_path_video, scene_camera_path

    side = 128 if cfg.quick else 256
    scene, mesh = scene_frame_mesh(path, mesh_file, 128)
    train = scene.splits.get("train") or list(range(len(scene)))
    model, _ = load_checkpoint(ckpt)
    lod = choose_level_of_detail(model, mesh, scene, realtime_setting(scene), train)  # faces and sources: measured
    lines.append(lod.line())
    setting = lod.setting(realtime_setting(scene))  # each frame blends its nearest sources, as finetune scores
    frames = 8 if cfg.quick else 48
    cams = scene_camera_path(scene, "orbit", frames)
    cams = cams.rescaled(side / max(cams.width, cams.height))
    picks = [sorted(select_sources(scene, cams[i], train, min(setting["sources"] or len(train), len(train)))) for i in
             range(len(cams))]
    drawn = lod.drawn(mesh, scene.cameras[train])  # the measured level, decimated once
    video, images, times, faces = mesh_path_video(model, drawn, scene, cams, picks, out / "mesh_path" / "orbit.mp4",
                                                  setting=setting, face_budget=0)
    fps = 1.0 / statistics.median(times)
    write_image(out / "mesh_path" / "frame_0000.png", images[0])
    away = away_from_photos(model, mesh, scene, path, train, cams, out)
    numbers["mesh_path"] = {"fps": fps, "resolution": [cams.width, cams.height], "frames": len(cams),
                            "threads": torch.get_num_threads(), "source_views": setting["sources"], "blend": setting,
                            "faces_drawn": faces, "lod": lod.record(), "away": away}
    lines.append(f"mesh path: {fps:.1f} FPS at {cams.width}x{cams.height} ({torch.get_num_threads()} threads, {faces:,} "
                 f"faces drawn); {away['line']}")
    return mesh_path_page(video, fps, cams, away, out)


def mesh_path_page(video: Path, fps: float, cams, away: dict, out: Path):
    """The report's "Real-time mesh path" section: the orbit video, its speed, its score and the worst frame."""
    import torch

    from omnirecon.engine.report import Section
    from omnirecon.mesh.defects import MAX_ANGLE

    return (Section("Real-time mesh path")
            .text(f"The Omni-Recon mesh rendered with the appearance branch, one surface point per pixel, source "
                  f"features encoded once: {fps:.1f} FPS at {cams.width}x{cams.height} (median of {len(cams)} frames, "
                  f"{torch.get_num_threads()} torch threads, this machine). `omnirecon bench` compares it with the "
                  f"volumetric path. Against the generator's exact images at the orbit's poses: {away['psnr']:.2f} dB; "
                  f"{away['defect_any']:.1%} of the frames' pixels lie on faces no photo supports (fills, faces no "
                  f"training view sees within {MAX_ANGLE:g} degrees of their normal, fragments).")
            .figure(video, out, f"mesh-path orbit, {len(cams)} frames", 320)
            .figure(out / "mesh_path" / "worst_frame.png", out, f"worst frame ({away['worst_frame']}): exact | mesh "
                    "path | unsupported faces (fills red, unseen blue, fragments yellow)", 480))


def away_from_photos(model, mesh, scene, path: Path, train: list[int], cams, out: Path) -> dict:
    """The orbit's frames scored against the procedural scene's exact images and by their defect shares
    (:func:`omnirecon.engine.extrapolation.score_frames`); the worst frame goes to ``mesh_path/worst_frame.png``."""
    import numpy as np

    from omnirecon.data.io import write_image  # lazy: demo --help stays fast
    from omnirecon.engine.extrapolation import procedural_truth, score_frames  # lazy: demo --help stays fast
    from omnirecon.mesh.defects import DefectCounter  # lazy: demo --help stays fast

    truth = procedural_truth(path, scene, cams)
    scored = score_frames(model, mesh, scene, train, cams, truth, keep_images=True)
    away = scored.summary()
    worst = away["worst_frame"]
    with DefectCounter(mesh, scene.cameras[train], scene.bounds) as counter:
        tiles = [(truth[worst].numpy() * 255 + 0.5).astype(np.uint8)] if truth is not None else []
        write_image(out / "mesh_path" / "worst_frame.png",
                    np.concatenate([*tiles, scored.images[worst], counter.picture(cams[worst])], 1))
    away.setdefault("psnr", float("nan"))
    away["line"] = (f"against the exact images {away['psnr']:.2f} dB, {away['defect_any']:.1%} of the pixels on faces "
                    f"no photo supports (worst frame {away['worst_frame']}: {away['worst_defect']:.1%})")
    return away


def finetune_section(cfg: DemoConfig, path: Path, ckpt: Path, mesh_file: Path, out: Path, numbers: dict,
                     lines: list[str]):
    """Fine-tune the mesh path for 30 s (quick: 3 s) and show the held-out gain."""
    from omnirecon.engine.report import Section  # lazy: demo --help stays fast
    from omnirecon.workflows.finetune import FinetuneConfig, run_finetune  # lazy: demo --help stays fast
    from omnirecon.workflows.finetune_curve import curve_table

    seconds = 3.0 if cfg.quick else 30.0
    r = run_finetune(FinetuneConfig(ckpt=ckpt, scene=path, seconds=seconds, eval_at=(0.0, 10.0, seconds),
                                    num_views=min(cfg.num_views, 3), mesh=mesh_file, out=out / "finetune",
                                    resolution=64 if cfg.quick else None, max_held_out=2 if cfg.quick else 4))
    c = r["curve"]
    # the pixels the mesh covers (inside the masks): what tuning the appearance can change
    key = "psnr_covered" if "psnr_covered" in c[0] else "psnr"
    numbers["finetune"] = {"seconds": seconds, "metric": key, "before": c[0][key], "after": c[-1][key],
                           "gain_db": c[-1][key] - c[0][key], "steps": c[-1]["steps"],
                           "whole_image": [c[0]["psnr"], c[-1]["psnr"]]}
    numbers["finetune"]["coverage"] = r["coverage"]
    lines.append(f"fine-tune {seconds:.0f} s: held-out PSNR on the mesh's pixels {c[0][key]:.2f} -> {c[-1][key]:.2f} dB, "
                 f"whole image {c[0]['psnr']:.2f} -> {c[-1]['psnr']:.2f} dB (coverage {r['coverage']:.0%}; the best "
                 "state on validation views is kept)")
    return (Section("Fine-tuning the mesh path")
            .text(f"`omnirecon finetune` for {seconds:.0f} s (wall clock): {' + '.join(r['tuned'])} (lr {r['lr']:g}), "
                  f"on the training views through the fixed mesh. Held-out PSNR over the pixels the mesh covers "
                  f"{c[0][key]:.2f} dB before, {c[-1][key]:.2f} dB after ({c[-1][key] - c[0][key]:+.2f} dB, "
                  f"{c[-1]['steps']} steps); over the whole image {c[0]['psnr']:.2f} -> {c[-1]['psnr']:.2f} dB; "
                  f"coverage {r['coverage']:.0%} of the held-out pixels lie on the mesh (the rest: {r['fill']} fill). "
                  "Tuning returns its best state on validation views (a state replaces the start only when it gains "
                  "on the whole image and on the objects there), so it never ends below the start there.")
            .table(*curve_table(c))
            .figure(out / "finetune" / "curve.png", out, "test and validation PSNR against seconds of tuning", 360)
            .figure(out / "finetune" / "before_after.png", out, "GT | before | after", 360))


def lift_section(cfg: DemoConfig, path: Path, scene, ckpt: Path, out: Path, numbers: dict, lines: list[str]):
    """Lift edges (and, on procedural scenes, labels) into held-out views with the model's blend weights."""
    import json

    from omnirecon.engine.report import Section  # lazy: demo --help stays fast
    from omnirecon.workflows.lift import LiftConfig  # lazy: demo --help stays fast

    section = Section("Lifting 2-D predictions into 3-D").text(
        f"Predict-then-blend with {ckpt.name}: a 2-D predictor runs on the {min(cfg.num_views, 3)} source views and "
        "its maps are blended into the held-out view with the model's own colour weights; render-then-predict "
        "runs the predictor on the rendered image instead.")
    predictors = ["sobel"] + (["oracle-labels"] if scene.labels is not None else [])
    rows = []
    for name in predictors:
        folder = out / f"lift_{name}"
        LiftConfig(ckpt=ckpt, scene=str(path), predictor=name, num_views=min(cfg.num_views, 3), out=folder).run()
        res = json.loads((folder / "metrics.json").read_text())
        sc = res["scenes"][0]
        mean = sc["mean"]
        numbers.setdefault("lift", {})[name] = mean
        metric = "miou" if "miou" in (mean.get("lift") or {}) else "fscore"
        lift_v = (mean.get("lift") or {}).get(metric)
        rtp_v = (mean.get("render") or {}).get(metric)
        rows.append([name, "mIoU (%)" if metric == "miou" else "edge F-score",
                     "–" if lift_v is None else round(lift_v, 3), "–" if rtp_v is None else round(rtp_v, 3)])
        panels = sorted((folder / sc["name"]).glob("*_panel.png"))
        if panels:
            section.figure(panels[0], out, f"{name}: target | render | lifted | ... (see {folder.name}/)", 420)
        lines.append(f"lift {name}: {metric} {lift_v if lift_v is None else round(lift_v, 3)} (predict-then-blend), "
                     f"{rtp_v if rtp_v is None else round(rtp_v, 3)} (render-then-predict)")
    section.table(["predictor", "metric", "predict-then-blend", "render-then-predict"], rows)
    return section


def overview_figure(out: Path) -> Path | None:
    """One strip of the demo's pictures (first orbit frames, meshes, lifted maps) as ``overview.png``.

    Tiles whose files a run did not produce (a missing checkpoint, no labels) are left out; returns
    None when there is nothing to show. The README's picture is this file.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omnirecon.data.io import atomic_path, read_image  # lazy: demo --help stays fast

    def first(pattern: str) -> Path | None:
        found = sorted(out.glob(pattern))
        return found[0] if found else None

    tiles = [(first("orbit_gpnr-tiny/frames/*.png"), "GPNR novel view"),
             (first("orbit_omnirecon-tiny/frames/*.png"), "Omni-Recon novel view"),
             (out / "mesh_omnirecon-tiny_preview.png", "Omni-Recon mesh"),
             (out / "mesh_path" / "frame_0000.png", "real-time mesh path"),
             (first("lift_sobel/*/*_lift.png"), "lifted edges"),
             (first("lift_oracle-labels/*/*_lift.png"), "lifted labels")]
    tiles = [(p, t) for p, t in tiles if p is not None and p.is_file()]
    if not tiles:
        return None
    fig, axes = plt.subplots(1, len(tiles), figsize=(2.2 * len(tiles), 2.5), dpi=110, squeeze=False)
    for ax, (p, title) in zip(axes[0], tiles):
        ax.imshow(read_image(p))
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    path = out / "overview.png"
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
