"""Where gpnr-tiny loses to ibrnet-tiny: the two shipped checkpoints on the same views and sources (issue 47).

    python -m bench train_gpnr_gap --threads 1

A diagnosis, not a lever: no training and nothing chosen on these numbers. Per target view (`cpu` protocol, 64 px,
K = 3, the protocol's sources) both checkpoints render the same view; recorded are PSNR (whole image), the mean
brightness of render and ground truth, the share of *dark leaks* (pixels bright in the ground truth, luminance
> 0.6, rendered dark, < 0.3), of gross errors (luminance off by more than 0.5) and of pixels no source view sees at
any sample depth (gpnr-tiny's ``valid``), plus each scene's normalised geometry (camera distance from the content
centre, horizontal field of view, aspect, near / far). Scenes: dtu_scan24 / dtu_scan37 (where the deficit was
measured; final-table scenes, looked at here only to describe the failure), the held-out views of the real training
scenes (validation), and lego and chair again with a black background (``BLACK``). Writes
bench/results/train_gpnr_gap.json and a picture of dtu_scan37 (sources on top, then ground truth | gpnr-tiny |
ibrnet-tiny per target).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from bench.train_tiny import REAL, SEED, SHARED

ROOT = Path(__file__).resolve().parents[1]
MODELS = ("gpnr-tiny", "ibrnet-tiny")
DTU = ["neus_dtu/dtu_scan24", "neus_dtu/dtu_scan37"]
BLACK = ["blender/lego", "blender/chair"]
"""Validation scenes also scored with a black instead of a white background behind the object (the content test:
does a uniform black region beside bright content make gpnr-tiny leak, as DTU's black backdrop does)."""
FIGURE = ROOT / "bench" / "results" / "figures" / "train_gpnr_gap_dtu_scan37.png"


def luminance(rgb):
    """``# [..., 3] -> [...]`` Rec. 601 luma."""
    return rgb[..., 0] * 0.299 + rgb[..., 1] * 0.587 + rgb[..., 2] * 0.114


def view_stats(pred, gt, seen) -> dict:
    """PSNR, mean brightness and dark-leak share of one render ``pred # [H, W, 3]`` against ``gt``; ``seen # [H, W]``
    pixels some source sees."""
    mse = float(((pred - gt) ** 2).mean())
    dark = (luminance(gt) > 0.6) & (luminance(pred) < 0.3)
    gross = (luminance(gt) - luminance(pred)).abs() > 0.5
    return {"psnr": round(-10 * math.log10(max(mse, 1e-10)), 3), "mean": round(float(luminance(pred).mean()), 3),
            "gt_mean": round(float(luminance(gt).mean()), 3), "dark_leak": round(float(dark.float().mean()), 4),
            "gross": round(float(gross.float().mean()), 4), "unseen": round(float((~seen).float().mean()), 4)}


def geometry(scene) -> dict:
    """Normalised camera layout: distance of the cameras from the content centre, horizontal field of view."""
    centres = scene.cameras.centers.double()
    fx = float(scene.cameras.K[0, 0, 0])
    return {"camera_distance": round(float(centres.norm(dim=-1).mean()), 3),
            "hfov_deg": round(2 * math.degrees(math.atan(scene.width / 2 / fx)), 1),
            "aspect": round(scene.width / scene.height, 3),
            "near": round(float(scene.near.float().median()), 3), "far": round(float(scene.far.float().median()), 3)}


def score_scene(models: dict, es, k: int, pictures: list | None) -> list[dict]:
    from omnirecon.cameras import closest_point_to_axes
    from omnirecon.engine.protocols import targets_and_pool
    from omnirecon.engine.views import select_sources, view_metric
    from omnirecon.rays import Sources

    scene = es.scene
    targets, pool = targets_and_pool(es.protocol, scene, None)
    fixed = dict(es.protocol.fixed_sources)
    center = closest_point_to_axes(scene.cameras) if view_metric(scene) == "angle" else None
    rows = []
    for t in targets:
        src = list(fixed[k]) if k in fixed else select_sources(scene, scene.cameras[t], pool, k, center)
        renders = {}
        for name, model in models.items():
            out = model.render_view(model.encode(Sources.from_scene(scene, src)), scene.cameras[t])
            renders[name] = (out["rgb"].float().clamp(0, 1), out["valid"].bool())
        seen = renders["gpnr-tiny"][1]
        rows.append({"target": t, "sources": src,
                     **{name: view_stats(rgb, scene.images[t], seen) for name, (rgb, _) in renders.items()}})
        if pictures is not None:
            pictures.append((scene, src, t, [rgb for rgb, _ in renders.values()]))
    return rows


def eval_scene(rel: str, background: str | None):
    """The `cpu` protocol's scene ``rel`` (under the shared data), with another ``background`` behind the masked
    object when given (named ``<scene> (<background> background)``)."""
    import dataclasses

    from omnirecon.engine.scenes import load_at_resolution, prepare_scenes

    es = prepare_scenes([str(SHARED / rel)], protocol_set="cpu")[0]
    if background is None:
        return es
    scene = load_at_resolution(SHARED / rel, es.protocol.long_side, background)
    return dataclasses.replace(es, name=f"{es.name} ({background} background)", scene=scene)


def picture(pictures: list, dest: Path) -> None:
    """Sources on the top row, then ground truth | gpnr-tiny | ibrnet-tiny per target (4x nearest upscaling)."""
    import numpy as np
    from PIL import Image

    scene, src = pictures[0][0], pictures[0][1]
    top = np.concatenate([scene.images[s].numpy() for s in src], 1)
    rows = [np.concatenate([scene.images[t].numpy(), *[r.numpy() for r in renders]], 1)
            for _, _, t, renders in pictures]
    width = max(top.shape[1], rows[0].shape[1])
    pad = [np.pad(x, ((0, 0), (0, width - x.shape[1]), (0, 0)), constant_values=1.0) for x in [top, *rows]]
    img = (np.concatenate(pad, 0) * 255).round().astype(np.uint8)
    dest.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img).resize((img.shape[1] * 4, img.shape[0] * 4), Image.NEAREST).save(dest)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--num-views", type=int, default=3, help="source views K")
    a = p.parse_args(argv)
    import torch

    from omnirecon.engine.machine import load_model
    from omnirecon.provenance import provenance

    torch.set_num_threads(a.threads)
    models = {m: load_model(ROOT / "checkpoints" / m, None)[0] for m in MODELS}
    cpu = time.process_time()
    result = {"num_views": a.num_views, "scenes": {}, "geometry": {}}
    for rel, background in [(r, None) for r in DTU + REAL] + [(r, "black") for r in BLACK]:
        es = eval_scene(rel, background)
        pictures = [] if es.name == "dtu_scan37" else None
        result["scenes"][es.name] = {"role": "final table (diagnosis only)" if rel in DTU else "validation"
                                     + (f", {background} background" if background else ""),
                                     "views": score_scene(models, es, a.num_views, pictures)}
        result["geometry"][es.name] = geometry(es.scene)
        if pictures:
            picture(pictures, FIGURE)
            result["figure"] = str(FIGURE.relative_to(ROOT))
        print(es.name, json.dumps(summary(result["scenes"][es.name]["views"])), flush=True)
    for name, s in result["scenes"].items():
        s["mean"] = summary(s["views"])
    result.update(cpu_s=round(time.process_time() - cpu, 1), provenance=provenance(SEED))
    dest = ROOT / "bench" / "results" / "train_gpnr_gap.json"
    tmp = dest.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(dest)
    print(f"wrote {dest}")


def summary(views: list[dict]) -> dict:
    """Per model: the views' mean of each statistic (PSNR as the mean of the views' PSNR)."""
    return {m: {k: round(sum(v[m][k] for v in views) / len(views), 3) for k in views[0][m]} for m in MODELS}
