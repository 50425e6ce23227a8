"""``omnirecon reconstruct``: photos, a video or a posed scene in; a mesh, a tuned model, an export and a
report page out. It composes the other workflows, in this order, into ``--out``::

    scene/        `omnirecon process` (only when PATH is a folder of photos or a video)
    mesh.ply/.glb `omnirecon mesh` with the checkpoint, in the scene's input frame (+ preview, metrics)
    finetune/     `omnirecon finetune` of the mesh path on the scene, with the tuned checkpoint
    export/       `omnirecon export` (baked PLY/GLB + the web viewer bundle; `omnirecon view export/viewer`)
    index.html    the report: camera rig, mesh preview, PSNR-vs-time curve, before/after, timings

Not yet here (issue 17): the all-view mesh of the geometry issue (the mesh uses --num-views sources),
the MP4 of a smooth camera path rendered by the mesh path at the photos' resolution.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, fields
from pathlib import Path

import tyro

from omnirecon.capture.colmap_sfm import SfmOptions
from omnirecon.capture.process import process, summary_lines
from omnirecon.data import detect_format, load_scene
from omnirecon.engine.machine import ThreadsConfig
from omnirecon.engine.report import Section, write_report
from omnirecon.errors import InputError
from omnirecon.workflows.export import ExportConfig, run_export
from omnirecon.workflows.finetune import FinetuneConfig, run_finetune
from omnirecon.workflows.inspect import draw_cameras
from omnirecon.workflows.mesh import MeshConfig, run_mesh


@dataclass(kw_only=True)
class ReconstructConfig(SfmOptions, ThreadsConfig):
    """From a folder of photos (or a video, or a scene with poses) to a mesh, a tuned model, a web
    viewer and a report page: process (COLMAP), mesh, finetune, export, report."""

    source: tyro.conf.Positional[Path | None] = None
    """Folder of photos, a video file, or a scene folder that already has poses (any supported format)."""
    out: Path = Path("outputs/reconstruct")
    """Output folder (see the module docstring for what goes in it)."""
    ckpt: Path = Path("checkpoints/omnirecon-tiny")
    """Omni-Recon checkpoint that meshes, is fine-tuned and exported."""
    num_views: int = 3
    """Source views of the mesh and the model."""
    resolution: int | None = None
    """Long side in pixels of the images meshed, tuned and exported (default: the scene's eval protocol)."""
    finetune_seconds: float = 60.0
    """Fine-tuning budget in seconds (0: skip fine-tuning and export the checkpoint as it is)."""
    masks: Path | None = None
    """Photos only: masks named like the photos, features only inside them (turntable captures)."""
    fps: float = 2.0
    """Video only: frames sampled per second."""
    viewer: bool = True
    """Write the web viewer bundle (needs three.js: `npm install` in omnirecon/viewer)."""
    overwrite: bool = False
    """Replace an existing scene/ folder in --out."""


def _is_scene(path: Path) -> bool:
    try:
        detect_format(path)
        return True
    except InputError:
        return False


def run_reconstruct(cfg: ReconstructConfig, log=print) -> dict:
    """Run the steps of the module docstring; returns the record written to ``out/reconstruct.json``."""
    if cfg.source is None:
        raise InputError("no input given", None, "pass a folder of photos, a video or a scene folder")
    if not cfg.ckpt.is_dir():
        raise InputError("checkpoint folder does not exist", cfg.ckpt, "pass an omnirecon-* checkpoint (--ckpt)")
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    record: dict = {"source": str(cfg.source), "ckpt": str(cfg.ckpt)}

    t = time.perf_counter()
    if Path(cfg.source).is_dir() and _is_scene(cfg.source):
        scene_dir = Path(cfg.source)
        record["process"] = None
    else:
        scene_dir = out / "scene"
        options = SfmOptions(**{f.name: getattr(cfg, f.name) for f in fields(SfmOptions)})
        summary = process(cfg.source, scene_dir, options, fps=cfg.fps, overwrite=cfg.overwrite, masks=cfg.masks)
        record["process"] = summary
        for line in summary_lines(summary):
            log(line)
    seconds["process"] = time.perf_counter() - t

    t = time.perf_counter()
    meshed = run_mesh(MeshConfig(scene=scene_dir, ckpt=cfg.ckpt, num_views=cfg.num_views,
                                 out=(out / "mesh.ply", out / "mesh.glb"), resolution=cfg.resolution,
                                 threads=cfg.threads))
    record["mesh"] = {k: meshed.get(k) for k in ("faces", "vertices", "metrics", "files") if k in meshed}
    seconds["mesh"] = time.perf_counter() - t
    log(f"mesh: {', '.join(meshed['files'])}")

    ckpt = cfg.ckpt
    if cfg.finetune_seconds > 0:
        t = time.perf_counter()
        tuned = run_finetune(FinetuneConfig(ckpt=cfg.ckpt, scene=scene_dir, seconds=cfg.finetune_seconds,
                                            num_views=cfg.num_views, mesh=out / "mesh.ply", out=out / "finetune",
                                            resolution=cfg.resolution, save=True, threads=cfg.threads))
        record["finetune"] = {"curve": tuned["curve"], "gain_db": tuned["gain_db"]}
        ckpt = out / "finetune" / "checkpoint"
        seconds["finetune"] = time.perf_counter() - t
        log(f"finetune: held-out PSNR {tuned['curve'][0]['psnr']:.2f} -> {tuned['curve'][-1]['psnr']:.2f} dB")

    t = time.perf_counter()
    exported = run_export(ExportConfig(scene=scene_dir, ckpt=ckpt, num_views=cfg.num_views, mesh=out / "mesh.ply",
                                       out=out / "export", viewer=cfg.viewer, resolution=cfg.resolution,
                                       threads=cfg.threads))
    record["export"] = {"files": exported.get("files", []), "out": exported["out"]}
    seconds["export"] = time.perf_counter() - t

    t = time.perf_counter()
    record["report"] = str(write_page(out, scene_dir, record, seconds))
    seconds["report"] = time.perf_counter() - t
    record["seconds"] = {k: round(v, 2) for k, v in seconds.items()}
    (out / "reconstruct.json").write_text(json.dumps(record, indent=1, default=str))
    return record


def write_page(out: Path, scene_dir: Path, record: dict, seconds: dict) -> Path:
    """``out/index.html``: the rig, the mesh preview, the fine-tuning pictures, the numbers."""
    scene = load_scene(scene_dir)
    rig = out / "cameras.png"
    draw_cameras(scene, rig)
    sections = []
    s = Section("Cameras")
    p = record.get("process")
    if p:
        s.text(f"{p['images_registered']} of {p['images_given']} images registered by COLMAP; {p['points3D']} 3-D "
               f"points; mean reprojection error {p['mean_reprojection_error_px']:.3f} px.")
    s.figure(rig, out, f"{len(scene)} cameras, rig {scene.rig}, in the scene frame")
    sections.append(s)
    s = Section("Mesh")
    if (out / "mesh_preview.png").is_file():
        s.figure(out / "mesh_preview.png", out, "the mesh from the first source view")
    s.link(out / "mesh.glb", out, "mesh.glb (input frame)")
    sections.append(s)
    if record.get("finetune"):
        s = Section("Fine-tuning")
        for name, caption in (("curve.png", "held-out PSNR against seconds"),
                              ("before_after.png", "ground truth | before | after")):
            if (out / "finetune" / name).is_file():
                s.figure(out / "finetune" / name, out, caption)
        c = record["finetune"]["curve"]
        s.table(["seconds", "steps", "held-out PSNR (dB)"], [[x["seconds"], x["steps"], x["psnr"]] for x in c])
        sections.append(s)
    s = Section("Timings")
    s.table(["stage", "seconds"], [[k, round(v, 2)] for k, v in seconds.items()])
    if (out / "export" / "viewer").is_dir():
        s.text(f"Open the viewer: omnirecon view {out / 'export' / 'viewer'}")
    sections.append(s)
    return write_report(out, f"omnirecon reconstruct: {Path(record['source']).name}", sections)
