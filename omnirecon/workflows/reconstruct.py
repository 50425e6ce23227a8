"""What ``omnirecon reconstruct`` does: a capture in, a mesh, a tuned real-time mesh path, an export and
a report out, with one command.

Stages (each timed; the report lists them)::

    process     photos or a video -> a COLMAP scene (pycolmap; skipped when PATH already is a scene)
    mesh        depth from every view, each rendered from its own nearest sources, fused into a mesh
    finetune    Omni-Recon's mesh path tuned on the scene's training views (a time budget)
    export      mesh.ply / mesh.glb with baked colours and the web-viewer bundle (`omnirecon view DIR`)
    path        a smooth camera path rendered by the tuned mesh path at the photos' own resolution (MP4)
    report      index.html: the camera rig, the mesh, the video, held-out scores and timings

Outputs in ``--out DIR``: ``scene/`` (when processed), ``mesh.ply`` (+ metrics and preview),
``finetune/`` (curve, tuned checkpoint), ``export/`` (PLY, GLB, ``viewer/``), ``path.mp4``,
``cameras.png``, ``reconstruct.json`` and ``index.html``. The folder is taken with
:func:`omnirecon.outputs.claim` (the one owner of the ``--out`` checks: never inside or around an input,
one run at a time, ``--overwrite`` replaces only a folder this tool wrote): built in ``OUT.partial`` beside it
and swapped in at the end, so a failed or interrupted run leaves the previous folder or none. Each finished stage
up to the export is kept there (:class:`~omnirecon.workflows.stages.Stages`: what it depended on, its record, its
files; the mesh stage also its meshes, exactly): after a failure the error names the stage and what is kept, and
the next run of the command continues from the first stage whose input files or options changed. Every
record in it names files inside it relative to ``--out`` (``scene``, ``export/mesh.glb``), so no record
points into the work folder. One :class:`Capture` goes from stage to stage: the scene folder, the side its images
are used at, the meshes (in memory, as read back from the kept copy, so a resumed run and an uninterrupted one go on
alike; ``mesh.ply`` is written once, for the user) and the checkpoint; every scene and checkpoint a stage reads is
read from disk once in a run (:mod:`omnirecon.engine.held`). ``--out`` is claimed here alone: the process stage
writes its scene into the claimed work folder.

Size: the stages, the record and page they make, and their errors in this command's terms, in one place.
"""

from __future__ import annotations

import statistics
import sys
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import tyro

from omnirecon.cameras import closest_point_to_axes
from omnirecon.data import detect_format
from omnirecon.data.io import write_image, write_json
from omnirecon.data.scene import Scene
from omnirecon.engine.checkpoint import load_checkpoint
from omnirecon.engine.held import holding
from omnirecon.engine.machine import MachineConfig, ShippedCheckpoint
from omnirecon.engine.report import Section, write_report
from omnirecon.engine.scenes import load_at_resolution, object_masks, photo_side
from omnirecon.engine.shipped import checkpoint_folder
from omnirecon.engine.views import select_sources
from omnirecon.errors import InputError
from omnirecon.mesh.confidence import NoDepth
from omnirecon.mesh.defects import MAX_ANGLE
from omnirecon.options import (
    CameraModel,
    CameraPath,
    CaptureInput,
    OutPath,
    Overwrites,
    PhotoSize,
    Resumes,
    SourceViews,
    ViewerBundle,
    check_options,
    command_defaults,
)
from omnirecon.outputs import claim, relative_to, write_marker
from omnirecon.provenance import provenance
from omnirecon.scene_kind import scene_kind
from omnirecon.trajectory import nearest_photo_degrees
from omnirecon.workflows.export import ExportConfig, run_export
from omnirecon.workflows.finetune import FinetuneConfig, run_finetune
from omnirecon.workflows.finetune_curve import curve_table
from omnirecon.workflows.inspect import draw_cameras
from omnirecon.workflows.mesh import MeshConfig, run_mesh
from omnirecon.workflows.render import mesh_path_video
from omnirecon.workflows.stages import StageRunner, Stages, files_digest


@dataclass
@command_defaults(out=Path("outputs/reconstruct"), frames=48, resume=True)
class ReconstructConfig(CaptureInput, CameraModel, OutPath, Overwrites, SourceViews, ShippedCheckpoint, PhotoSize,
                        CameraPath, Resumes, ViewerBundle, MachineConfig):
    """Reconstruct a capture with one command: camera poses (when PATH holds photos or a video), a mesh
    from every view, a short fine-tune of the real-time mesh path, an export for the web viewer, a
    camera-path video at the photos' resolution and a report page (open DIR/index.html, or
    `omnirecon view DIR/export`)."""

    path: tyro.conf.Positional[Path]
    """A folder of photos, a video, or a scene folder in any supported format."""
    mesh_resolution: int | None = None
    """Long side of the images meshed (default: the photos' own, at most 512: stereo matches at it, the model's
    depth for stereo's holes is rendered at 128)."""
    finetune_seconds: float = 60.0
    """Fine-tuning budget in wall seconds (0: export and render the checkpoint as it is)."""


KEPT = {"process": "the poses", "mesh": "the mesh", "finetune": "the tuned model", "export": "the export"}
"""The stages a failed run keeps (the rest run again), in the user's words."""


def stage_depends(cfg: ReconstructConfig) -> dict[str, dict]:
    """What each kept stage's result depends on (:class:`~omnirecon.workflows.stages.Stages`; later stages depend on
    the earlier ones too): the input files (a digest of names, sizes and times) and the options that change it."""
    return {"process": {"PATH's files": files_digest(cfg.path), "--masks' files": files_digest(cfg.masks),
                        "--fps": cfg.fps, "--camera-model": cfg.camera_model},
            "mesh": {"--ckpt's files": files_digest(cfg.ckpt), "--num-views": cfg.num_views,
                     "--mesh-resolution": cfg.mesh_resolution},
            "finetune": {"--finetune-seconds": cfg.finetune_seconds, "--resolution": cfg.resolution},
            "export": {"--viewer": cfg.viewer}}


def run_reconstruct(cfg: ReconstructConfig, say=print) -> dict:
    """Run every stage (those a failed run kept in ``OUT.partial`` are read back instead); returns the record written to
    ``reconstruct.json`` (plus ``lines``). An error names the stage and what the run keeps for the next."""
    check_options("reconstruct", cfg)  # the numbers (omnirecon/options.py); here for callers other than the CLI
    if not Path(cfg.path).exists():
        raise InputError("input does not exist", cfg.path, "pass a folder of photos, a video or a scene folder")
    cfg = replace(cfg, ckpt=checkpoint_folder(cfg.ckpt))  # a path, or a shipped name such as omnirecon-tiny
    if not (cfg.ckpt / "meta.json").is_file():
        raise InputError("not a checkpoint folder (no meta.json)", cfg.ckpt, "pass e.g. --ckpt omnirecon-tiny")
    out = Path(cfg.out)
    with claim(out, "reconstruct", inputs=(cfg.path, cfg.ckpt, cfg.masks), mode="resume",
               overwrite=cfg.overwrite, say=say) as owned:
        stages = Stages(owned.work, stage_depends(cfg), cfg.resume, say)
        try:
            record = relative_to(_stages(cfg, owned.work, stages), owned.work)  # claim does the same to the records
        except BaseException as e:
            raise failed(cfg, e, stages) from e
    record["report"] = str(out / "index.html")
    return record


def failed(cfg: ReconstructConfig, e: BaseException, stages: Stages) -> BaseException:
    """The error to raise for ``e``, raised in ``stages.current``: an :class:`InputError` names the stage and what
    is kept for the next run (in its fix); any other error is raised as it is, after a note saying the same."""
    kept = [KEPT[n] for n in stages.kept if n in KEPT and stages.kept[n]["files"]]
    if not kept:
        stages.discard()  # nothing worth keeping (a scene folder's "process" wrote nothing): the folder goes
    keep = f"kept in {stages.work}: {' and '.join(kept)}; rerun the same command to continue" if kept else ""
    if not isinstance(e, InputError):
        if keep:
            print(f"omnirecon: note: {keep}", file=sys.stderr)
        return e
    e = stage_error(cfg, e, stages)
    return InputError(f"{stages.current} stage: {e.what}", e.path if e.path is not None else cfg.path,
                      "; ".join(x for x in (e.fix, keep) if x))


def stage_error(cfg: ReconstructConfig, e: InputError, stages: Stages) -> InputError:
    """``e`` in this command's terms: what the poses were, the likely cause and a fix with ``reconstruct``'s options
    (the mesh library words its errors for ``omnirecon mesh``)."""
    processed = (stages.result("process") or {}).get("processed")
    posed = (f"poses for {processed['images_registered']}/{processed['images_given']} "
             f"{'frames' if processed.get('kind') == 'video' else 'photos'}; " if processed else "")
    video = bool(processed and processed.get("kind") == "video")
    more = ("walk slower around the subject or raise --fps (more frames that overlap)" if video else
            "photograph textured surfaces, each photo overlapping its neighbours by more than half")
    if stages.current != "mesh":  # a process stage's error is about the photos: as it is (PATH is no scene yet)
        return e
    side = cfg.mesh_resolution or photo_side(stages.work / "scene" if processed else Path(cfg.path))
    if isinstance(e, NoDepth):
        if e.lost == "source":
            fix = f"{more}, or raise --mesh-resolution (now {side} px: stereo matches finer texture at more pixels)"
            cause = "the photos give stereo nothing to match (too little texture or overlap, or too few pixels)"
        elif e.lost == "occluded":
            fix = f"{more}; check the poses with `omnirecon inspect {stages.work / 'scene'}`" if processed else e.fix
            cause = "the poses and the depth do not agree"
        else:
            fix, cause = e.fix, "the photos show only the scene's known background colour"
        return InputError(f"{posed}{e.what}: likely cause: {cause}", e.path, fix)
    if stages.current == "mesh" and e.what.startswith("the mesh is empty"):
        return InputError(f"{posed}{e.what}", e.path, f"{more}, or raise --mesh-resolution (now {side} px)")
    return e


class Laps:
    """Wall and process CPU seconds and peak resident memory per stage (``seconds``, ``cpu_seconds``,
    ``peak_rss_mb``; every thread counts in the CPU clock, and so do the SfM children's, which ``process`` runs in a
    child process: :data:`~omnirecon.capture.process.CHILD_CPU_SECONDS`): ``lap(name)`` closes the stage that ran
    since the previous lap. The memory is the kernel's high-water mark (``VmHWM``), reset at each lap (Linux; elsewhere
    ``peak_rss_mb`` stays empty)."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.cpu_seconds: dict[str, float] = {}
        self.peak_rss_mb: dict[str, float] = {}
        self._clock, self._cpu = time.perf_counter(), _cpu_seconds()
        _reset_peak_rss()

    def __call__(self, name: str) -> dict[str, float]:
        """Close stage ``name``; returns its measurements (``seconds``, ``cpu_seconds``, ``peak_rss_mb``)."""
        now, cpu = time.perf_counter(), _cpu_seconds()
        self.seconds[name] = round(now - self._clock, 2)
        self.cpu_seconds[name] = round(cpu - self._cpu, 2)
        peak = _peak_rss_mb()
        if peak is not None and _reset_peak_rss():
            self.peak_rss_mb[name] = peak
        self._clock, self._cpu = now, cpu
        return {"seconds": self.seconds[name], "cpu_seconds": self.cpu_seconds[name],
                **({"peak_rss_mb": self.peak_rss_mb[name]} if name in self.peak_rss_mb else {})}


def _cpu_seconds() -> float:
    """This process's CPU seconds plus its SfM children's."""
    from omnirecon.capture.process import CHILD_CPU_SECONDS

    return time.process_time() + CHILD_CPU_SECONDS[0]


def give_back_memory() -> None:
    """Collect garbage and hand the freed heap back to the system (glibc's ``malloc_trim``; nothing elsewhere): a
    stage's large freed arrays otherwise stay in this process's resident memory under the next stages'. On
    ethiopianHead the process stayed at 4.8 GB after the mesh stage and fine-tuning went past 6.5 GB on top."""
    import ctypes
    import gc

    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _peak_rss_mb() -> float | None:
    """This process's peak resident memory since the last reset, MB (None off Linux)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        pass
    return None


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-memory mark of this process (``/proc/self/clear_refs``); False where it cannot."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


@dataclass
class Capture:
    """What ``reconstruct`` holds once and hands from stage to stage: the scene folder the stages read (PATH, or the
    scene the process stage posed), the side its images are used at, the meshes, the checkpoint the later stages
    use, and every scene and checkpoint read, held (:mod:`omnirecon.engine.held`: each read from disk once)."""

    work: Path
    """The work folder (``OUT.partial``): the one folder the run writes, claimed once by :func:`run_reconstruct`."""
    ckpt: Path
    """The checkpoint the stages use: ``--ckpt``, the tuned one once the finetune stage saved it."""
    path: Path | None = None
    """The scene folder (after the process stage)."""
    processed: dict | None = None
    """The process stage's record (``None`` when PATH already is a scene)."""
    side: int = 0
    """Long side (px) of the images tuned, scored, exported and rendered."""
    meshes: dict = field(default_factory=dict)
    """The mesh in the scene's frame (``scene``) and in the input's (``input``)."""
    held: dict = field(default_factory=dict)
    """The scenes and checkpoints read, by what was read (``omnirecon.engine.held``)."""
    reads: Counter = field(default_factory=Counter)
    """Reads from disk per kind (``scene``, ``scene_probe``, ``checkpoint``)."""

    def scene(self) -> Scene:
        """The scene at :attr:`side`, normalised (held: read once)."""
        return load_at_resolution(self.path, self.side)

    def model(self):
        """``(model, meta)`` of :attr:`ckpt` (held: loaded once; a copy each time)."""
        return load_checkpoint(self.ckpt)


def _stages(cfg: ReconstructConfig, out: Path, stages: Stages) -> dict:
    """Every stage into ``out`` (the work folder), each kept in ``stages`` when done (or read back from it), with one
    :class:`Capture` holding what they share; returns the record (``lines``: what to print)."""
    cap = Capture(work=out, ckpt=Path(cfg.ckpt))
    with holding(cap.held, cap.reads):
        record = _run_stages(cfg, cap, stages)
    record["reads"] = dict(cap.reads)  # what was read from disk (not in reconstruct.json: a resumed run reads less)
    return record


def _run_stages(cfg: ReconstructConfig, cap: Capture, stages: Stages) -> dict:
    lines: list[str] = []
    lap = Laps()
    run = StageRunner(stages, lap, lines)
    cap.processed = run("process", lambda said: {"processed": process_stage(cfg, cap.work, said)[1]})["processed"]
    cap.path = cap.work / "scene" if cap.processed else Path(cfg.path)

    def mesh(said: list[str]) -> dict:
        meshed = mesh_stage(cfg, cap, said)
        stages.keep_meshes("mesh", meshed.pop("meshes"))  # scene and input frame: the next stages read no mesh file
        give_back_memory()  # the fusion grid and the marching-cubes mesh are gone: the next stages start lower
        return meshed

    meshed = run("mesh", mesh)
    cap.meshes = stages.meshes("mesh")
    cap.side = cfg.resolution or photo_side(cap.path)
    tuned = run("finetune", lambda said: finetune_stage(cfg, cap, said))
    cap.ckpt = cap.work / "finetune" / "checkpoint" if cfg.finetune_seconds > 0 else Path(cfg.ckpt)
    exported = run("export", lambda said: export_stage(cfg, cap, tuned))
    fill_from = (meshed.get("completion") or {}).get("surface_faces") if meshed.get("options", {}).get("surface") \
        != "coherent" else None
    stages.current = "path"
    path = path_stage(cfg, cap, lines, tuned, fill_from)
    lap("path")
    stages.current = "report"
    out = cap.work
    draw_cameras(path["scene"], out / "cameras.png")
    record = {"provenance": provenance(seed=0), "input": str(cfg.path), "scene": str(cap.path),
              "process": cap.processed, "checkpoint": str(cfg.ckpt), "mesh": {k: meshed[k] for k in
                                                                             ("vertices", "depth_maps", "views", "masks")},
              "finetune": {"resolution": cap.side, "curve": tuned["curve"]}, "export": exported["files"],
              "path": {"frames": len(path["cams"]), "resolution": [path["cams"].width, path["cams"].height],
                       "fps": path["fps"], "lod": path["lod"], "kind": path["kind"], "nearest_photo_degrees": path["nearest_photo_degrees"],
                       "blend": path["setting"], "defects": path["defects"]},
              "seconds": lap.seconds, "cpu_seconds": lap.cpu_seconds, "peak_rss_mb": lap.peak_rss_mb,
              "resumed": run.resumed, "threads": torch.get_num_threads()}
    lap("report")
    record["seconds"]["total"] = round(sum(lap.seconds.values()), 2)
    write_json(out / "reconstruct.json", record)
    write_page(cfg, cap.path, meshed, tuned["curve"], path, record, " ".join(lines[-2:]), out, tuned["line"])
    record["lines"] = lines
    return record


def process_stage(cfg: ReconstructConfig, out: Path, lines: list[str]) -> tuple[Path, dict | None]:
    """The scene: PATH itself when it is one, else photos or a video posed into ``out/scene``."""
    try:
        detect_format(Path(cfg.path))
        return Path(cfg.path), None
    except InputError:
        from omnirecon.capture.colmap_sfm import SfmOptions  # lazy: pycolmap is the optional `capture` extra
        from omnirecon.capture.process import process, summary_lines  # lazy: as above

        sfm = SfmOptions(camera_model=cfg.camera_model, feature_threads=cfg.threads or torch.get_num_threads())
        processed = process(Path(cfg.path), out / "scene", sfm, fps=cfg.fps,  # the rest of COLMAP on 1: reproducible
                            masks=cfg.masks, claimed=True)  # out: the work folder run_reconstruct claimed
        lines += summary_lines(processed)
        return out / "scene", processed


def mesh_stage(cfg: ReconstructConfig, cap: Capture, lines: list[str]) -> dict:
    """A mesh from every view (``mesh.ply``), carved and cleaned with the object masks on object captures that
    have them (``mesh --masks``: photos processed with ``--masks``, DTU); the record holds the meshes in memory
    under ``meshes``."""
    masks = object_masks(cap.path)
    mesh_cfg = MeshConfig(scene=cap.path, ckpt=cfg.ckpt, views=("all",), num_views=cfg.num_views,
                          out=(cap.work / "mesh.ply",), resolution=cfg.mesh_resolution or photo_side(cap.path),
                          masks=masks, device=cfg.device, threads=cfg.threads, chunk=cfg.chunk)
    meshed = run_mesh(mesh_cfg)
    lines.append(f"mesh: {meshed['vertices']:,} vertices from {meshed['depth_maps']} depth maps"
                 + (" (carved and cleaned with the object masks)" if masks else ""))
    return meshed


def finetune_stage(cfg: ReconstructConfig, cap: Capture, lines: list[str]) -> dict:
    """Fine-tune at the photos' resolution into ``finetune/`` of the work folder; returns its record."""
    budget = cfg.finetune_seconds
    tuned = run_finetune(FinetuneConfig(ckpt=cap.ckpt, scene=cap.path, seconds=max(budget, 1e-3),
                                        eval_at=(0.0, *(t for t in (10.0, 30.0, 60.0) if t < budget), budget),
                                        num_views=cfg.num_views, mesh=cap.work / "mesh.ply", resolution=cap.side,
                                        out=cap.work / "finetune", save=budget > 0, threads=cfg.threads),
                         mesh=cap.meshes["scene"])
    curve = tuned["curve"]
    objects = (f"; on the object masks {curve[0]['psnr_masked']:.2f} -> {curve[-1]['psnr_masked']:.2f} dB"
               if "psnr_masked" in curve[0] else "")
    tuned["line"] = (f"held-out mesh-path PSNR {curve[0]['psnr']:.2f} dB before, {curve[-1]['psnr']:.2f} dB after "
                     f"{curve[-1]['seconds']:g} s of fine-tuning (coverage {tuned['coverage']:.0%}{objects})")
    lines.append(tuned["line"])
    return tuned


def export_stage(cfg: ReconstructConfig, cap: Capture, tuned: dict | None = None) -> dict:
    """``out/export``: the baked mesh and the viewer bundle (over the sources ``tuned``, the finetune record in
    ``out/finetune``, blended, starting with the setting it scored); marks ``finetune/`` and ``export/`` as outputs."""
    out = cap.work
    record = out / "finetune" if tuned and (out / "finetune" / "curve.json").is_file() else None
    exported = run_export(ExportConfig(scene=cap.path, ckpt=cap.ckpt, mesh=out / "mesh.ply", out=out / "export",
                                       resolution=cap.side, finetune=record, viewer=cfg.viewer, device=cfg.device,
                                       threads=cfg.threads, chunk=cfg.chunk), mesh=cap.meshes["input"])
    for sub, verb in (("finetune", "finetune"), ("export", "export")):  # each output folder carries the marker
        write_marker(out / sub, verb)
    return exported


def path_stage(cfg: ReconstructConfig, cap: Capture, lines: list[str], tuned: dict | None = None,
               fill_from: int | None = None) -> dict:
    """``path.mp4``: the camera path a user watches (:func:`~omnirecon.engine.extrapolation.user_path`: the photos'
    arc and past its ends, or the walk) through the tuned mesh path, blended as ``tuned`` (the finetune record) scored
    (:func:`~omnirecon.mesh.ibr.realtime_setting`); each frame's defect shares (:mod:`omnirecon.mesh.defects`;
    completion's fills are the faces from ``fill_from`` on), the first and the worst frame as pictures; returns
    ``{"scene", "cams", "video", "fps", "lod", "kind", "setting", "defects", "worst"}`` (``lod``: the faces and sources
    drawn, :func:`~omnirecon.engine.lod.choose_level_of_detail`)."""
    from omnirecon.engine.extrapolation import user_path  # lazy: fast --help
    from omnirecon.engine.lod import choose_level_of_detail
    from omnirecon.mesh.ibr import realtime_setting

    scene, (model, _), mesh, out = cap.scene(), cap.model(), cap.meshes["scene"], cap.work
    train = scene.splits.get("train") or list(range(len(scene)))
    cams, kind = user_path(scene, train, cfg.frames)
    lod = choose_level_of_detail(model, mesh, scene, realtime_setting(scene, tuned), train)  # measured per mesh
    lines.append(lod.line())
    setting = lod.setting(realtime_setting(scene, tuned))  # the sources per frame it chose
    picks = [sorted(select_sources(scene, cams[i], train, min(setting["sources"] or len(train), len(train)))) for i in
             range(len(cams))]
    drawn = lod.drawn(mesh, scene.cameras[train])  # the measured level, decimated once
    video, images, times, faces = mesh_path_video(model, drawn, scene, cams, picks, out / "path.mp4", setting=setting,
                                                  face_budget=0)
    defects, worst = path_defects(mesh, scene, train, cams, images, fill_from, out)
    fps = 1.0 / statistics.median(times)
    center = closest_point_to_axes(scene.cameras) if scene_kind(scene).object else scene.bounds.double().mean(0)
    away = nearest_photo_degrees(cams.c2w, scene.cameras[train], center)  # [F]: how far frames extrapolate
    reach = {"median": round(float(away.median()), 1), "max": round(float(away.max()), 1)}
    mean = {k: round(float(np.mean([d[k] for d in defects])), 4) for k in defects[0]}
    lines.append(f"camera path ({kind}): {len(cams)} frames at {cams.width}x{cams.height}, {reach['median']:g} "
                 f"degrees from the nearest photo (median; at most {reach['max']:g}), mesh path {fps:.1f} FPS "
                 f"(median frame at {cams.width}x{cams.height}, {torch.get_num_threads()} threads, {faces:,} of "
                 f"{len(mesh.faces):,} faces drawn; source features encoded once per source set)")
    lines.append(f"away from the photos: {mean['any']:.1%} of the path's pixels on faces no photo supports (fills "
                 f"{mean['fill']:.1%}, seen by no photo within {MAX_ANGLE:g} degrees of their normal "
                 f"{mean['unseen']:.1%}, fragments {mean['small']:.1%}); worst frame {worst} "
                 f"{defects[worst]['any']:.1%} (path_worst_frame.png)")
    return {"scene": scene, "cams": cams, "video": video, "fps": fps, "faces_drawn": faces, "kind": kind, "nearest_photo_degrees": reach,
            "lod": lod.record(),
            "setting": setting, "defects": {"mean": mean, "worst_frame": worst, "per_frame": [d["any"] for d in defects]},
            "worst": worst}


def path_defects(mesh, scene, train: list[int], cams, images: list, fill_from: int | None,
                 out: Path) -> tuple[list[dict], int]:
    """Each path frame's defect shares and the worst frame's index; writes ``path_first_frame.png`` and
    ``path_worst_frame.png`` (the frame beside its defect faces: fills red, unseen blue, fragments yellow)."""
    from omnirecon.mesh.defects import DefectCounter  # lazy: fast --help

    with DefectCounter(mesh, scene.cameras[train], scene.bounds, fill_from) as counter:
        defects = [counter(cams[i]) for i in range(len(cams))]
        worst = int(np.argmax([d["any"] for d in defects]))
        write_image(out / "path_first_frame.png", np.concatenate([images[0], counter.picture(cams[0])], 1))
        write_image(out / "path_worst_frame.png", np.concatenate([images[worst], counter.picture(cams[worst])], 1))
    return defects, worst


def write_page(cfg: ReconstructConfig, scene_path: Path, meshed: dict, curve: list[dict], path: dict, record: dict,
               path_line: str, out: Path, tuned_line: str = "") -> None:
    """``index.html``: the rig, the mesh, the video, the held-out scores (PSNR beside coverage) and the timings."""
    scene = path["scene"]
    notes = []
    if record.get("process"):  # the photos were posed here: the turntable hint, when it applies
        from omnirecon.capture.process import motion_lines  # lazy: pycolmap is the optional `capture` extra

        notes = [line.removeprefix("note: ") for line in motion_lines(record["process"])]
    sections = [
        Section("Capture").text(" ".join([f"{len(scene)} views of {scene_path.name} ({scene.rig} rig).", *notes]))
        .figure(out / "cameras.png", out, "camera rig", 480),
        Section("Mesh").text(f"{meshed['vertices']:,} vertices fused from {meshed['depth_maps']} depth maps "
                             f"({cfg.num_views} sources each)").figure(out / "mesh_preview.png", out, "mesh", 480),
        Section("Real-time mesh path").text(path_line).figure(path["video"], out, "camera path", 480)
        .figure(out / "path_first_frame.png", out, "first frame | its faces no photo supports (fills red, unseen blue, "
                "fragments yellow)", 640)
        .figure(out / "path_worst_frame.png", out, f"worst frame ({path['worst']}) | its unsupported faces", 640),
        Section("Held-out views").text(f"{tuned_line[:1].upper()}{tuned_line[1:]}: coverage is the fraction of "
                                       "held-out pixels on real surface. PSNR of the mesh path against seconds of "
                                       "fine-tuning: held-out test views (never tuned on) and validation views "
                                       "(training views kept out of tuning; the state returned is the best there, "
                                       "the start included).")
        .table(*curve_table(curve))
        .figure(out / "finetune" / "curve.png", out, "test and validation PSNR vs fine-tuning time", 480)
        .figure(out / "finetune" / "before_after.png", out, "ground truth | before | after", 640),
        Section("Timings").table(["stage", "seconds", "peak memory (MB)", "kept from an earlier run (its seconds)"],
                                 [[k, v, record.get("peak_rss_mb", {}).get(k, ""), record.get("resumed", {}).get(k, "")]
                                  for k, v in record["seconds"].items()]),
    ]
    write_report(out, f"omnirecon reconstruct: {Path(cfg.path).name}", sections)
