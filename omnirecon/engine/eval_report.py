"""Results of ``omnirecon eval``: per-view rows -> per-scene and per-protocol means, JSON, Markdown, panels.

Means: a scene's number is the mean over its target views (PSNR averaged in dB per view, as the
NeRF literature does); a protocol's number is the mean over its scenes. ``seconds_per_view`` is
wall time of encoding the sources plus rendering, without scoring.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from torch import Tensor

from omnirecon.data.io import atomic_path, write_image, write_json
from omnirecon.provenance import markdown_header

METRIC_ORDER = ("psnr", "ssim", "st_lpips_alex", "lpips_alex", "psnr_masked", "depth_abs_rel", "depth_delta1")
"""Column order of the tables; each metric is followed by its ``_aux`` variant when present."""
ERROR_VMAX = 0.25
"""Mean absolute RGB error mapped to the top of the error colour scale (fixed, so maps compare)."""
DIGITS = {"psnr": 2, "psnr_masked": 2, "ssim": 4, "st_lpips_alex": 4, "lpips_alex": 4, "depth_abs_rel": 4,
          "depth_delta1": 3}
GEOMETRY_KEYS = ("chamfer", "accuracy", "completeness", "chamfer_rel", "fscore", "mask_iou", "fused_depth_abs_rel",
                 "seconds", "completeness_dropped")
"""Columns of the geometry table (``omnirecon eval --geometry``), lengths in input units."""


def metric_keys(rows: list[dict]) -> list[str]:
    """The metric columns present in ``rows``, in table order."""
    present = set().union(*(r.keys() for r in rows)) if rows else set()
    return [k for m in METRIC_ORDER for k in (m, f"{m}_aux") if k in present]


def _mean(values: list[float]) -> float:
    """Mean that ignores NaN (empty masks) and keeps ``inf`` (identical images)."""
    finite = [v for v in values if not math.isnan(v)]
    return float(np.mean(finite)) if finite else math.nan


def collect(records: list[dict], jobs: list[dict], ks: list[int], header: dict) -> dict:
    """Assemble the result dict from the scene records and the finished jobs."""
    for job in jobs:
        views = job["views"]
        keys = metric_keys(views)
        job["record"]["settings"][str(job["k"])] = {
            "views": views,
            "mean": {k: _mean([v[k] for v in views if k in v]) for k in keys},
            "seconds_per_view": _mean([v["seconds"] for v in views]),
        }
        if "geometry" in job:
            job["record"]["settings"][str(job["k"])]["geometry"] = job["geometry"]
    all_seconds = [v["seconds"] for job in jobs for v in job["views"]]
    return {**header, "num_views": ks, "scenes": records, "means": protocol_means(records, ks),
            "seconds_per_view": _mean(all_seconds) if all_seconds else None}


def protocol_means(records: list[dict], ks: list[int]) -> dict[str, dict[str, dict]]:
    """``{protocol: {K: means over its scenes}}`` of scene records whose ``settings`` are filled."""
    means: dict[str, dict[str, dict]] = {}
    for proto in dict.fromkeys(r["protocol"] for r in records):
        recs = [r for r in records if r["protocol"] == proto]
        for k in map(str, ks):
            done = [r["settings"][k] for r in recs if k in r["settings"]]
            if not done:
                continue
            keys = metric_keys([s["mean"] for s in done])
            means.setdefault(proto, {})[k] = {
                **{m: _mean([s["mean"][m] for s in done if m in s["mean"]]) for m in keys},
                "seconds_per_view": _mean([s["seconds_per_view"] for s in done]),
                "scenes": len(done),
            }
            geo = [s["geometry"] for s in done if "geometry" in s]
            if geo:
                means[proto][k]["geometry"] = {g: _mean([r[g] for r in geo if g in r]) for g in GEOMETRY_KEYS
                                               if any(g in r for r in geo)}
    return means


def _jsonable(x):
    """Replace non-finite floats (not valid JSON): ``inf`` -> ``"inf"``, NaN -> ``None``."""
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else ("inf" if x > 0 else "-inf")
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def _fmt(key: str, value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if isinstance(value, float) and math.isinf(value):
        return "inf"
    return f"{value:.{DIGITS.get(key.removesuffix('_aux'), 4)}f}"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in rows]


def markdown(result: dict) -> str:
    """The Markdown page: provenance, per-protocol means, per-scene table, notes."""

    model = result["model"]
    lines = [f"# Evaluation: {model.get('name')}", "", markdown_header(result["provenance"]), "",
             f"Model: preset `{model.get('preset')}`, checkpoint `{model.get('checkpoint')}`"
             + (f", step {model['step']}" if model.get("step") is not None else "") + ".", ""]
    if result.get("non_protocol"):
        lines += [f"**Not protocol numbers:** overrides {result['non_protocol']}.", ""]
    means = [(p, k, m) for p, per_k in result["means"].items() for k, m in per_k.items()]
    keys = metric_keys([m for _, _, m in means])
    lines += ["## Means over scenes", ""]
    lines += _table(["protocol", "K", "scenes", *keys, "s/view"],
                    [[p, k, str(m["scenes"]), *(_fmt(c, m.get(c)) for c in keys), f"{m['seconds_per_view']:.2f}"]
                     for p, k, m in means])
    rows, keys = [], metric_keys([s["mean"] for r in result["scenes"] for s in r["settings"].values()])
    for r in result["scenes"]:
        for k, s in r["settings"].items():
            rows.append([r["name"], r["protocol"], k, str(len(s["views"])), *(_fmt(c, s["mean"].get(c)) for c in keys),
                         f"{s['seconds_per_view']:.2f}"])
    lines += ["", "## Per scene", ""] + _table(["scene", "protocol", "K", "targets", *keys, "s/view"], rows)
    geo = [(r["name"], k, s["geometry"]) for r in result["scenes"] for k, s in r["settings"].items() if "geometry" in s]
    if geo:
        cols = [g for g in GEOMETRY_KEYS if any(g in row for _, _, row in geo)]
        lines += ["", "## Geometry (meshes; lengths in input units; chamfer_rel = Chamfer / extent of the scored GT "
                  "surface)", ""]
        lines += _table(["scene", "K", "views", *cols],
                        [[name, k, " ".join(map(str, row["views"])), *(_fmt(c, row.get(c)) for c in cols)]
                         for name, k, row in geo])
    notes = [f"- {r['name']}: K={k} skipped: {why}" for r in result["scenes"] for k, why in r["skipped"].items()]
    notes += [f"- `{m}` not reported: {why}" for m, why in result.get("unavailable", {}).items()]
    if notes:
        lines += ["", "## Notes", ""] + notes
    lines += ["", "Protocols: docs/evaluation.md. PSNR in dB over [0, 1] images (mean of per-view values); SSIM "
              "11x11 Gaussian, sigma 1.5; `st_lpips_alex` is shift-tolerant LPIPS, not comparable with LPIPS; "
              "`_aux` columns score GPNR's other head `rgb_aux` (the feature head where `rgb` is the blended "
              "source colours, `output=colors` as in gpnr-tiny; the blend otherwise).", ""]
    return "\n".join(lines)


def write(result: dict, out: Path) -> None:
    """Write ``results.json`` and ``results.md`` into ``out`` (atomically)."""
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "results.json", _jsonable(result))
    with atomic_path(out / "results.md") as tmp:
        tmp.write_text(markdown(result))


def summary_lines(result: dict) -> list[str]:
    """One line per protocol and K for the terminal."""
    lines = []
    for proto, per_k in result["means"].items():
        for k, m in per_k.items():
            vals = ", ".join(f"{c} {_fmt(c, m[c])}" for c in metric_keys([m]))
            lines.append(f"{proto} K={k} ({m['scenes']} scenes): {vals}; {m['seconds_per_view']:.2f} s/view")
            if "geometry" in m:
                lines.append(f"{proto} K={k} mesh: " + ", ".join(f"{g} {_fmt(g, v)}" for g, v in m["geometry"].items()))
    for r in result["scenes"]:
        for k, why in r["skipped"].items():
            lines.append(f"{r['name']}: K={k} skipped ({why})")
    return lines


def error_map(gt: Tensor, pred: Tensor, vmax: float = ERROR_VMAX) -> np.ndarray:
    """Mean absolute RGB error as an ``inferno`` heat map, 0 -> black, ``vmax`` and above -> yellow. ``# [H, W, 3]``"""
    import matplotlib

    err = (pred.float() - gt.float()).abs().mean(-1).numpy() / vmax  # [H, W]
    return matplotlib.colormaps["inferno"](np.clip(err, 0, 1))[..., :3].astype(np.float32)


def write_panel(path: Path, gt: Tensor, pred: Tensor, gap: int = 2) -> None:
    """``GT | render | |error|`` side by side (white gaps), as a PNG."""
    h = gt.shape[0]
    white = np.ones((h, gap, 3), np.float32)
    panel = np.concatenate([gt.float().numpy(), white, pred.float().numpy(), white, error_map(gt, pred)], axis=1)
    write_image(path, panel)
