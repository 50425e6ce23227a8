"""Source views on validation: how many (K) and how far from the target, for the shipped tiny checkpoints.

Two questions of issue 26, answered on validation data only (the scenes of ``bench train_levers``: procedural
seeds 901000, 901002, 901004 and the held-out views of lego, chair, fox, ethiopianHead; ``cpu`` protocol, 64 px):

* ``--part count``: omnirecon-tiny (trained at K = 4 only) at K = 3, 4 and 10, and at K = 10 with its
  ``render_views`` render option off and on (render from the 4 sources nearest the target).
* ``--part wide``: every shipped model on the object-rig validation scenes with the nearest sources (as the
  protocol picks them) against DTU-like wide baselines: each target's K sources are the nearest pool views at
  least ``min_deg`` away (angle around the look-at centre). DTU's protocol leaves the nearest source 29 degrees
  from its targets on average at K = 3 (its fixed sources 23, 24, 33) and 12 degrees at K = 10, against 3-5
  degrees on lego and ethiopianHead; this measures which model loses most when the baselines widen.

    python -m bench train_views                      # both parts, bench/results/train_views.json
    python -m bench train_views --part wide --models gpnr-tiny ibrnet-tiny

Results: PSNR (whole image; over the mask too where the scene has one) per scene and setting, the means, the
process CPU-seconds and the load average, with a provenance header. Held-out scenes are never read here.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
from pathlib import Path

import torch

from bench.train_levers import val_scenes
from bench.train_tiny import SEED

ROOT = Path(__file__).resolve().parents[1]
COUNT_SETTINGS = (("K3", 3, None), ("K4", 4, None), ("K10", 10, None), ("K10_render_views4", 10, 4))
"""(name, K, omnirecon-tiny's ``render_views``: None = off) of the ``count`` part."""
WIDE_SETTINGS = ((3, 0.0), (3, 25.0), (10, 0.0), (10, 10.0))
"""(K, min_deg) of the ``wide`` part: 0 = the nearest pool views (the protocol's choice)."""


def cpu_now() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_utime + resource.getrusage(resource.RUSAGE_SELF).ru_stime


def load(model: str):
    from omnirecon.engine.checkpoint import fingerprint, load_checkpoint

    ckpt = ROOT / "checkpoints" / model
    net, meta = load_checkpoint(ckpt)
    return net.eval(), {"name": model, "step": meta["step"], **fingerprint(ckpt)}


def render_scores(net, scene, target: int, sources: list[int]) -> dict:
    from omnirecon import metrics
    from omnirecon.rays import Sources

    with torch.no_grad():
        out = net.render_view(net.encode(Sources.from_scene(scene, sources)),
                              scene.cameras[[target]].to(dtype=scene.images.dtype))
    pred = out["rgb"].float().clamp(0, 1)
    row = {"psnr": float(metrics.psnr(pred, scene.images[target]))}
    if scene.masks is not None:
        row["psnr_masked"] = float(metrics.psnr(pred, scene.images[target], scene.masks[target]))
    return row


def mean_rows(rows: list[dict]) -> dict:
    return {k: round(sum(r[k] for r in rows) / len(rows), 3) for k in rows[0]}


def sources_for(es, target: int, pool: list[int], k: int, min_deg: float) -> list[int]:
    """The ``k`` pool views nearest ``target`` at least ``min_deg`` away (angle around the look-at centre on
    object rigs, as the protocol's nearest views; 0: the protocol's own choice)."""
    from omnirecon.cameras import closest_point_to_axes, view_distances
    from omnirecon.engine.views import select_sources

    cams = es.scene.cameras
    centre = closest_point_to_axes(cams)
    if min_deg <= 0:
        return select_sources(es.scene, cams[target], pool, k, centre)
    d = view_distances(cams[[target]], cams[pool], by="angle", center=centre)[0].rad2deg()
    d = torch.where(d < min_deg, torch.full_like(d, float("inf")), d)
    return [pool[i] for i in d.topk(k, largest=False).indices.tolist()]


def run_settings(net, scenes, settings) -> dict:
    """``{scene: {setting name: mean scores}}`` for ``settings`` = [(name, K, min_deg)]."""
    from omnirecon.engine.protocols import targets_and_pool

    out: dict = {}
    for es in scenes:
        targets, pool = targets_and_pool(es.protocol, es.scene)
        for name, k, min_deg in settings:
            rows = [render_scores(net, es.scene, t, sources_for(es, t, pool, k, min_deg)) for t in targets]
            out.setdefault(es.name, {})[name] = mean_rows(rows)
    return out


def means(per_scene: dict) -> dict:
    """Mean PSNR over the procedural and over the real validation scenes, per setting."""
    out: dict = {}
    for group, pick in (("procedural", lambda n: n.startswith("scene_")), ("real", lambda n: not n.startswith("scene_"))):
        names = [n for n in per_scene if pick(n)]
        for setting in next(iter(per_scene.values())):
            vals = [per_scene[n][setting]["psnr"] for n in names if setting in per_scene[n]]
            if vals:
                out.setdefault(setting, {})[group] = round(sum(vals) / len(vals), 3)
    return out


def count_part(scenes) -> dict:
    net, info = load("omnirecon-tiny")
    shipped = net.cfg.render_views
    start = cpu_now()
    per_scene: dict = {}
    for name, k, cap in COUNT_SETTINGS:
        net.cfg = dataclasses.replace(net.cfg, render_views=cap)
        for scene, row in run_settings(net, scenes, [(name, k, 0.0)]).items():
            per_scene.setdefault(scene, {}).update(row)
    net.cfg = dataclasses.replace(net.cfg, render_views=shipped)
    return {"checkpoint": info, "shipped_render_views": shipped, "settings": [list(s) for s in COUNT_SETTINGS],
            "scenes": per_scene, "means": means(per_scene), "cpu_s": round(cpu_now() - start, 1)}


def wide_part(scenes, models: list[str]) -> dict:
    obj = [s for s in scenes if s.scene.rig == "object"]
    settings = [(f"K{k}_min{m:g}deg", k, m) for k, m in WIDE_SETTINGS]
    out = {"scenes": [s.name for s in obj], "settings": [list(s) for s in settings], "models": {}}
    for model in models:
        net, info = load(model)
        start = cpu_now()
        per_scene = run_settings(net, obj, settings)
        mean = {name: round(sum(v[name]["psnr"] for v in per_scene.values()) / len(per_scene), 3) for name, _, _ in settings}
        out["models"][model] = {"checkpoint": info, "scenes": per_scene, "mean": mean, "cpu_s": round(cpu_now() - start, 1)}
        print(model, mean, flush=True)
    return out


def main(argv: list[str] | None = None) -> None:
    from omnirecon.data.io import write_json
    from omnirecon.engine.scenes import prepare_scenes
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--part", nargs="+", choices=["count", "wide"], default=["count", "wide"])
    p.add_argument("--models", nargs="+", default=["gpnr-tiny", "ibrnet-tiny", "omnirecon-tiny"])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "train_views.json")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    torch.manual_seed(SEED)
    result = json.loads(a.out.read_text()) if a.out.is_file() else {}
    scenes = prepare_scenes(val_scenes(), protocol_set="cpu", cache=ROOT / "outputs" / "cache")
    if "count" in a.part:
        result["count"] = count_part(scenes)
        print("count", result["count"]["means"], flush=True)
    if "wide" in a.part:
        wide = wide_part(scenes, a.models)
        result["wide"] = {**result.get("wide", {}), **{k: v for k, v in wide.items() if k != "models"},
                          "models": {**result.get("wide", {}).get("models", {}), **wide["models"]}}
    result["provenance"] = provenance(SEED)
    write_json(a.out, result)
    print(f"wrote {a.out}")
