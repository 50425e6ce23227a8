"""Surface-guided volumetric rendering against the full path: CPU seconds and PSNR per shipped checkpoint.

    python -m bench guided                                  # 504-px long side, every shipped tiny model
    python -m bench guided --side 252 --models ibrnet-tiny --settings '{}' '{"band_samples": 12}'
    python -m bench guided --threads 2 --out bench/results/guided_2threads.json --figures  # both cores, pictures

For each shipped tiny checkpoint and each scene (fern, and one held-out procedural forward-facing scene
generated at ``--side``), one novel view (the protocol's first target, rendered from its ``--k`` nearest pool
views) is rendered by the full path (what ``omnirecon render`` runs without ``--guided.on``: the checkpoint's own
render options) and by the guided path with each ``--settings`` entry (``GuidedOptions`` fields over their
defaults; the prior is the model's own render at ``1 / prior_scale`` size, included in its time). Reported: process
CPU seconds and wall seconds of the encode and of each render at ``--threads`` torch threads (1 by default), PSNR of
each against the ground truth and of the guided render against the full one, and the share of pixels guided. Writes ``bench/results/guided.json`` with a
provenance header and the load average beside every row (``--out``: another ``guided*.json``, e.g. one per
scene run in parallel; the page shows each).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
MODELS = ("gpnr-tiny", "ibrnet-tiny", "omnirecon-tiny")
SYNTH_SEED = 900_004
"""A held-out procedural seed (the synth:eval range, never trained on)."""


def scenes(side: int) -> list[tuple[str, Path]]:
    from omnirecon.data.synth.generate import SynthOptions, generate_scene

    synth = generate_scene(ROOT / "outputs" / "cache" / "guided", SYNTH_SEED,
                           SynthOptions(rig="forward", views=12, resolution=side))
    return [("fern", ROOT.parent / "shared" / "data" / "llff" / "fern"), (f"synth_forward_{SYNTH_SEED}", synth)]


def view(path: Path, side: int, k: int):
    """(scene at ``side``, target index, its ``k`` nearest pool views, the target's camera and ground truth). A square
    target (procedural scenes) is cropped to 4:3 about its centre (the camera's principal point moved with it): the
    shape of a photo, e.g. 504x378."""
    from omnirecon.cameras import Cameras
    from omnirecon.data import detect_format
    from omnirecon.engine.protocols import protocol_for, targets_and_pool
    from omnirecon.engine.scenes import load_at_resolution
    from omnirecon.engine.views import select_sources

    scene = load_at_resolution(path, side)
    targets, pool = targets_and_pool(protocol_for(path, detect_format(path), "full"), scene)
    t = targets[0]
    cam, gt = scene.cameras[[t]].to(dtype=scene.images.dtype), scene.images[t]
    if cam.width == cam.height:
        h = cam.width * 3 // 4
        top = (cam.height - h) // 2
        cam = Cameras(cam.fx, cam.fy, cam.cx, cam.cy - top, cam.c2w, cam.width, h)
        gt = gt[top:top + h]
    return scene, t, select_sources(scene, scene.cameras[t], pool, k), cam, gt


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return round(float(-10 * torch.log10((a.float().clamp(0, 1) - b.float()).square().mean().clamp_min(1e-12))), 3)


def timed(fn):
    """(process CPU-s, wall s, ``fn()``) under ``no_grad``."""
    t0, w0 = time.process_time(), time.perf_counter()
    with torch.no_grad():
        out = fn()
    return round(time.process_time() - t0, 2), round(time.perf_counter() - w0, 2), out


def figure(path: Path, *images: torch.Tensor) -> None:
    """The images ``# [H, W, 3]`` side by side at half their size (ground truth | full path | guided)."""
    import torch.nn.functional as F

    from omnirecon.data.io import write_image

    row = torch.cat([im.float().clamp(0, 1) for im in images], 1).permute(2, 0, 1)[None]  # [1, 3, H, n W]
    write_image(path, F.interpolate(row, scale_factor=0.5, mode="area")[0].permute(1, 2, 0).numpy())


def measure(model_name: str, scene_name: str, scene, target: int, sources: list[int], cam, gt, settings: list[dict],
            figures: Path | None = None) -> list:
    """Rows of ``model_name`` on one view: the full path once, then each setting (with ``figures``: the first one's
    ground truth | full | guided picture into that folder)."""
    from omnirecon.engine.checkpoint import folder_for_size, load_checkpoint
    from omnirecon.models.guided import GuidedOptions, render_guided
    from omnirecon.rays import Sources

    # the weights `render` loads at this size (trained nearest it), for both rows: the guided cost on one set of weights
    folder = folder_for_size(ROOT / "checkpoints" / model_name, max(cam.width, cam.height))
    model, meta = load_checkpoint(folder)
    model.eval()
    enc_s, enc_wall, feats = timed(lambda: model.encode(Sources.from_scene(scene, sources)))
    full_s, full_wall, full = timed(lambda: model.render_view(feats, cam)["rgb"])
    base = {"model": model_name, "weights": f"{folder.relative_to(ROOT)} step {meta['step']}", "scene": scene_name,
            "size": [cam.width, cam.height], "target": target, "sources": sources, "threads": torch.get_num_threads(),
            "encode_cpu_s": enc_s, "encode_wall_s": enc_wall, "full_cpu_s": full_s, "full_wall_s": full_wall,
            "psnr_full": psnr(full, gt)}
    rows = []
    for i, spec in enumerate(settings):
        options = dataclasses.replace(GuidedOptions(on=True), **spec)
        g_s, g_wall, out = timed(lambda: render_guided(model, feats, cam, options))
        if figures is not None:  # the first setting's under the old name, the others numbered
            figure(figures / f"guided_{model_name}_{scene_name}{f'_{i}' if i else ''}.png", gt, full, out["rgb"])
        row = {**base, "setting": spec, "options": dataclasses.asdict(options.resolved(model)), "guided_cpu_s": g_s,
               "guided_wall_s": g_wall,
               "speedup": round(full_s / g_s, 2), "psnr_guided": psnr(out["rgb"], gt),
               "psnr_guided_vs_full": psnr(out["rgb"], full), "guided_share": round(float(out["guided"].float().mean()), 4),
               "upsampled_share": round(float(out["upsampled"].float().mean()), 4) if "upsampled" in out else 0.0,
               "loadavg": [round(x, 2) for x in os.getloadavg()]}
        row["dpsnr"] = round(row["psnr_guided"] - row["psnr_full"], 3)
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS))
    parser.add_argument("--side", type=int, default=504, help="long side of the rendered view and the sources, px")
    parser.add_argument("--k", type=int, default=3, help="source views")
    parser.add_argument("--settings", nargs="+", default=["{}"], help="GuidedOptions overrides, one JSON object each")
    parser.add_argument("--scenes", nargs="+", default=None, help="only these scene names (fern, synth_forward_...)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads of the encode and the renders (wall seconds are recorded beside CPU-s)")
    parser.add_argument("--figures", action="store_true",
                        help="write bench/results/figures/guided_<model>_<scene>[_<i>].png: ground truth | full | "
                             "setting i's guided render (no suffix: the first setting), at half size")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "guided.json",
                        help="results file; the page shows every bench/results/guided*.json")
    args = parser.parse_args(argv)
    from omnirecon.data.io import write_json
    from omnirecon.provenance import provenance

    torch.set_num_threads(args.threads)
    settings = [json.loads(s) for s in args.settings]
    result = {"provenance": provenance(seed=0, threads=args.threads), "threads": args.threads, "side": args.side,
              "k": args.k, "settings": settings,
              "loadavg_start": [round(x, 2) for x in os.getloadavg()], "rows": []}
    for name, path in scenes(args.side):
        if args.scenes and name not in args.scenes:
            continue
        scene, target, sources, cam, gt = view(path, args.side, args.k)
        for m in args.models:
            result["rows"] += measure(m, name, scene, target, sources, cam, gt, settings,
                                      HERE / "results" / "figures" if args.figures else None)
            write_json(args.out, result)  # partial results survive an interrupted run
    result["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    write_json(args.out, result)
    return result
