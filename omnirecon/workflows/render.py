"""``omnirecon render``: render a camera path through a scene to PNG frames and a video.

For each frame camera the model encodes the ``K`` scene views nearest to it (by angle around the
look-at centre for object rigs, by camera-centre distance otherwise; the same rule as
``omnirecon eval``) and renders the full frame in chunks. Outputs in ``--out``::

    frames/0000.png ...   one PNG per frame
    video.mp4             H.264 via imageio + imageio-ffmpeg (video.gif via Pillow when ffmpeg is missing)
    cameras.json          per frame: c2w (OpenCV, in the normalised scene frame of ``Scene.normalized``),
                          fx fy cx cy, and the source views used
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from omnirecon import trajectory
from omnirecon.cameras import Cameras, closest_point_to_axes
from omnirecon.data.io import atomic_path, write_image, write_json
from omnirecon.engine.machine import (
    GuidedRendering,
    MachineConfig,
    ModelChoice,
    load_model,
    pick_device,
    set_threads,
)
from omnirecon.engine.scenes import load_at_resolution
from omnirecon.engine.views import select_sources, view_metric
from omnirecon.errors import InputError
from omnirecon.models.fast import switches
from omnirecon.models.guided import render_guided
from omnirecon.options import (
    CameraPath,
    ImageSize,
    OutFolder,
    SceneInput,
    SourceViews,
    check_options,
    command_defaults,
)
from omnirecon.progress import progress_bar
from omnirecon.rays import Sources
from omnirecon.scene_kind import scene_kind


@dataclass
@command_defaults(num_views=10)
class RenderConfig(GuidedRendering, OutFolder, ModelChoice, SceneInput, SourceViews, ImageSize, CameraPath,
                   MachineConfig):
    """Render a camera path (orbit, LLFF-style spiral, or interpolation between scene cameras)
    through a scene with a checkpoint or the plane-sweep floor; writes PNG frames and a video."""

    path: Literal["orbit", "spiral", "interp"] = "orbit"
    """orbit: circle the scene centre at the cameras' mean distance/elevation; spiral: LLFF-style
    around the mean pose (forward-facing scenes); interp: through the scene cameras in order."""
    keyframes: tuple[int, ...] | None = None
    """interp: scene view indices to pass through, in order (default: up to 8 views evenly spaced)."""
    arc: float | None = None
    """orbit: degrees of the arc (360 = a closed loop); default: the arc the photos cover, swept there and back (a
    full loop when no gap between the cameras' azimuths is wider than 60 deg), as ``reconstruct``'s video: a full
    orbit of fox, photographed over 93 deg, put 32 of 48 frames more than 20 deg from any photo."""
    rots: float = 2.0
    """spiral: number of turns."""
    fps: int = 24
    """Frames per second of the video."""
    video: bool = True
    """Also write video.mp4 (or video.gif)."""
    render_pass: Literal["auto", "coarse", "fine"] = "auto"
    """Two-pass models (IBRNet, Omni-Recon): coarse renders the coarse pass only, fine both; auto: the
    checkpoint's choice (the shipped omnirecon-tiny: coarse, several times faster at no loss; ibrnet-tiny: fine, its
    coarse pass is faster but worse: `python -m bench tiny_levers`, BENCHMARKS "Render levers of the tiny presets").
    One-pass models ignore it."""
    samples: int | None = None
    """Samples per ray instead of the checkpoint's (GPNR: all of them, gpnr-tiny's default 24; two-pass models:
    the coarse pass's): fewer is faster."""
    precision: Literal["auto", "fp32", "bf16"] = "auto"
    """bf16: the per-sample networks under bf16 autocast (GPNR faster on CPUs with avx512_bf16 at the same
    PSNR; IBRNet and Omni-Recon gain nothing; several times slower on CPUs without it, e.g. AVX2 only); auto: the
    checkpoint's (gpnr-tiny: bf16) where the device computes bf16 natively, else fp32 (BENCHMARKS "Render levers of
    the tiny presets")."""

    def check(self) -> None:
        check_options("render", self)  # the numbers (omnirecon/options.py); here for callers other than the CLI
        self.guided.check()
        if self.out is not None and self.out.exists() and not self.out.is_dir():
            raise InputError("output path exists and is not a folder", self.out, "pass a folder for --out")


def default_out(cfg: RenderConfig) -> Path:
    """``--out``, or ``outputs/render/<scene>_<path>``."""
    return cfg.out or Path("outputs/render") / f"{Path(cfg.scene).name}_{cfg.path}"


def scene_camera_path(scene, kind: trajectory.PathKind, frames: int, keyframes: list[int] | None = None,
                      arc: float | None = 360.0, rots: float = 2.0, beyond: float = 0.0) -> Cameras:
    """:func:`omnirecon.trajectory.camera_path` through a :class:`~omnirecon.data.scene.Scene`: an orbit
    circles the point closest to the optical axes (object rigs) or the bounds centre (over ``arc`` degrees;
    ``None``: the arc the photos cover, reaching ``beyond`` degrees past its ends), a spiral spans the scene's near
    and far depths."""
    cams = scene.cameras
    center = closest_point_to_axes(cams) if scene_kind(scene).object else scene.bounds.double().mean(0)
    return trajectory.camera_path(cams, kind, frames, center, float(scene.near.min()), float(scene.far.max()),
                                  keyframes, arc, rots, beyond)


def camera_path(cfg: RenderConfig, scene) -> Cameras:
    """The frame cameras of ``cfg.path`` through ``scene`` (its resolution and intrinsics)."""
    if cfg.path == "interp":
        keys = list(cfg.keyframes) if cfg.keyframes else trajectory.default_keyframes(len(scene))
        bad = [k for k in keys if not 0 <= k < len(scene)]
        if bad or len(keys) < 2:
            raise InputError(f"--keyframes must name at least 2 views in 0..{len(scene) - 1}, got {keys}", scene.path,
                             "pass view indices as listed by `omnirecon inspect`")
    return scene_camera_path(scene, cfg.path, cfg.frames, list(cfg.keyframes or ()), cfg.arc, cfg.rots)


def render_levers(net, info: dict, cfg: RenderConfig) -> dict:
    """Apply ``--samples`` to the model's config (recorded in ``info``); returns ``render_view``'s options."""
    if cfg.samples is not None:
        key = next((k for k in ("render_samples", "render_coarse_samples", "coarse_samples") if hasattr(getattr(net, "cfg", None), k)), None)
        if key is not None:
            setattr(net.cfg, key, cfg.samples)
            info["render_samples"] = {key: cfg.samples}
    info["render_options"] = {"render_pass": cfg.render_pass, "precision": cfg.precision, "guided": asdict(cfg.guided.resolved(net))}
    return {} if cfg.render_pass == "auto" else {"fine_pass": cfg.render_pass == "fine"}


def run_render(cfg: RenderConfig) -> tuple[Path, Path | None]:
    """Render ``cfg``; returns the output folder and the video file (``None`` without ``cfg.video``)."""

    cfg.check()
    set_threads(cfg.threads)
    device = pick_device(cfg.device)
    scene = load_at_resolution(cfg.scene, cfg.resolution)
    # the weights trained nearest the render's size, full path or surface-guided
    net, info = load_model(cfg.ckpt, cfg.model, device, long_side=max(scene.width, scene.height))
    options = render_levers(net, info, cfg)
    if cfg.num_views > len(scene):
        raise InputError(f"--num-views {cfg.num_views} but the scene has {len(scene)} views", cfg.scene,
                         f"use --num-views {len(scene)} or fewer")
    out = default_out(cfg)
    cams = camera_path(cfg, scene)
    pool = list(range(len(scene)))
    center = closest_point_to_axes(scene.cameras) if view_metric(scene) == "angle" else None
    frames, records, key, features = [], [], None, None
    start = time.perf_counter()
    with progress_bar("render", "frames") as bar, torch.no_grad(), \
            switches(**({} if cfg.precision == "auto" else {"bf16_render": cfg.precision == "bf16"})):
        task = bar.add_task("render", total=len(cams))
        for i in range(len(cams)):
            src = select_sources(scene, cams[i], pool, cfg.num_views, center)
            if tuple(sorted(src)) != key:
                key = tuple(sorted(src))
                features = net.encode(Sources.from_scene(scene, sorted(src)).to(device))
            rgb = render_guided(net, features, cams[i].to(device=device, dtype=scene.images.dtype), cfg.guided,
                                cfg.chunk, **options)["rgb"]
            frame = (rgb.detach().float().cpu().clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)  # [H, W, 3]
            write_image(out / "frames" / f"{i:04d}.png", frame)
            frames.append(frame)
            c = cams[i]
            records.append({"c2w": c.c2w[0].tolist(), "fx": float(c.fx[0]), "fy": float(c.fy[0]),
                            "cx": float(c.cx[0]), "cy": float(c.cy[0]), "sources": src})
            bar.advance(task)
    seconds = time.perf_counter() - start
    write_json(out / "cameras.json", {"path": cfg.path, "scene": str(cfg.scene), "model": info, "num_views":
                                      cfg.num_views, "width": cams.width, "height": cams.height,
                                      "seconds_per_frame": seconds / len(cams), "frames": records})
    video = write_video(out / "video.mp4", frames, cfg.fps) if cfg.video else None
    print(f"{seconds / len(cams):.2f} s per frame")
    return out, video


def mesh_path_video(model, mesh, scene, cameras: Cameras, sources: list[list[int]], path: Path, fps: int = 24,
                    setting: dict | None = None, face_budget: int | None = None
                    ) -> tuple[Path, list[np.ndarray], list[float], int]:
    """Render ``cameras`` through ``mesh`` (scene frame) with the real-time mesh path
    (:class:`~omnirecon.mesh.ibr.MeshRenderer`; the blend and the fill ``finetune --blend auto --fill auto`` scores
    with (:func:`~omnirecon.mesh.ibr.scene_blend`: pixels no triangle covers take the scene's known background
    colour where it has one, else the far fill, which on the demo's black sky drew ghost copies of the objects;
    the angle blend on object captures), or ``setting`` (:func:`~omnirecon.mesh.ibr.realtime_setting`: what finetune
    scored with); the occlusion test on, as ``finetune
    --visibility``: without it a source that saw the ground behind an object painted the object's colour onto the
    ground) and write the video at ``path``.

    ``sources[i]``: the scene views frame ``i`` is rendered from; consecutive frames with the same views
    share one renderer, and every renderer one :class:`~omnirecon.mesh.frames.ViewCache` (one rasterizer, each view's
    occlusion depths once, each set of views encoded once: the frames are those of a renderer per set, bit for bit).
    The mesh is drawn with at most ``face_budget`` faces (default :data:`~omnirecon.mesh.ibr.REALTIME_FACE_BUDGET`; 0:
    the full mesh), decimated once (``mesh`` stays whole); the angle blend ranks each chunk's candidate sources
    (:data:`~omnirecon.mesh.ibr.REALTIME_FRAME_GRID`); up to 2 threads shade (torch's threads, one op each). Returns the video file, the 8-bit frames ``# [H, W, 3]``, the
    seconds of each frame (after one untimed warm-up frame) and the number of faces drawn."""
    from omnirecon.mesh.frames import ViewCache, render_frames
    from omnirecon.mesh.ibr import realtime_setting, video_options  # lazy: fast --help

    bg = tuple(scene.background) if scene.background is not None else (1.0, 1.0, 1.0)
    threads = torch.get_num_threads()
    opts = video_options(setting or realtime_setting(scene), bg, min(2, threads), face_budget)
    images, times = [], []
    start = 0
    torch.set_num_threads(1 if opts.workers > 1 else threads)  # parallel over chunks (MeshRenderOptions.workers)
    with ViewCache(model, mesh, scene, opts) as cache:
        faces = len(cache.rasterizer.faces)
        while start < len(cameras):
            end = start + 1
            while end < len(cameras) and list(sources[end]) == list(sources[start]):
                end += 1
            with cache.renderer(list(sources[start])) as r:
                frames, seconds = render_frames(r, cameras[start:end], warmup=start == 0)
            images += frames
            times += seconds
            start = end
    torch.set_num_threads(threads)
    return write_video(path, images, fps), images, times, faces


def write_video(path: Path, frames: list[np.ndarray], fps: int) -> Path:
    """Write ``frames`` (``# [H, W, 3]`` uint8) as H.264 MP4 via imageio-ffmpeg; without ffmpeg, as a
    GIF beside ``path`` via Pillow. Returns the file written."""
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401  (the bundled ffmpeg binary)
    except ImportError:
        return _write_gif(path.with_suffix(".gif"), frames, fps)
    # yuv420p needs even sides: pad by repeating the last row/column.
    h, w = frames[0].shape[:2]
    pad = ((0, h % 2), (0, w % 2), (0, 0))
    with atomic_path(path) as tmp:
        writer = imageio.get_writer(tmp, format="FFMPEG", fps=fps, codec="libx264", macro_block_size=1,
                                    pixelformat="yuv420p", output_params=["-crf", "18"])
        try:
            for f in frames:
                writer.append_data(np.pad(f, pad, mode="edge"))
        finally:
            writer.close()
    return path


def _write_gif(path: Path, frames: list[np.ndarray], fps: int) -> Path:
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    with atomic_path(path) as tmp:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
    return path
