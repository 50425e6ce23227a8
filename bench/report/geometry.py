"""BENCHMARKS.md section: Geometry from 3 source views (`python -m bench geometry`)."""

from __future__ import annotations

import json
import math
from pathlib import Path

from bench.report.common import GEOMETRY_MODELS, VIEW_CAP, num, prov, stale_note

ROWS = ("floor", "stereo", *GEOMETRY_MODELS[1:])
"""Rows in table order: the plane-sweep floor, classical stereo (no model), the shipped checkpoints."""
NO_RENDER = ("stereo",)
"""Rows that render no target view (a depth source without a model): no PSNR, no target depth."""
PARTS = ("target_renders", "depth", "mesh", "score", "write", "other", "total")


def section(results: Path) -> str | None:
    data = {m: json.loads((results / f"geometry_{m}.json").read_text()) for m in ROWS
            if (results / f"geometry_{m}.json").is_file()}
    if not data:
        return None
    first = next(iter(data.values()))
    n_synth = len(first["synth"]["scenes"])
    targets = first.get("synth_targets", 2)
    out = ["## Geometry from 3 source views (`python -m bench geometry`)", "",
           "`omnirecon eval --geometry`, K = 3, `full` protocols (128-px long side). A mesh per scene from the same 3 "
           "source views for every row, by `omnirecon mesh`'s pipeline with its default `fit` settings (recorded in "
           "each result as `mesh_options`): depth at the 3 views, confidence-weighted TSDF fusion (voxel from the maps' "
           "pixel footprint), marching cubes, mask and visibility cleaning, face budget, completion, all with the "
           "scenes' object masks (objects only; `omnirecon mesh --masks`). Depth per row: "
           "the model's fine-pass depth, or for **stereo** classical stereo with no model (OpenCV SGBM on pairs "
           "rectified from the poses, left-right check, sub-pixel disparity, votes across pairs; "
           "`omnirecon/mesh/stereo.py`), among the same 3 views only. Procedural: Chamfer distance (mean of accuracy "
           "and completeness, DTU-style sampling, outliers capped) against the exact mesh's observed surface; "
           "`Chamfer / extent` divides by the diagonal of that surface's bounding box; F-score at 1 % of the bounds "
           f"diagonal; silhouette IoU on {targets} held-out views per scene. Seconds: images to mesh (encode, depth, "
           "fuse, marching cubes, clean, complete), wall time on this CPU at 1 thread under the load the provenance "
           "names (the CPU table below is the load-free measure). PSNR and target depth are the model's own "
           "volumetric render of the held-out views, so stereo, which has no model to render with, shows `–` there "
           "(shading its mesh needs a model: see the mesh-path sections).", "",
           f"**Held-out procedural scenes** (mean of {n_synth}; lengths in the generator's units):", "",
           "Chamfer leaves out distances beyond its cap (2.5 % of the bounds diagonal, DTU's 20 mm), so a mesh "
           "that covers a small part of the surface accurately scores a small Chamfer: `GT beyond cap` (the fraction "
           "of ground-truth points farther than the cap from the mesh, left out of completeness) and the F-score say "
           "how much of the surface a row has. A mean marked `(n/N)` is over the n scenes with any surface within "
           "the cap; a scene where a row made no mesh at all counts 0 in F-score and IoU and 100 % beyond the cap.",
           "",
           "| row | Chamfer | accuracy | completeness | Chamfer / extent | GT beyond cap | F-score | silhouette IoU | "
           f"depth abs rel (targets) | images -> mesh (s) | PSNR ({targets} targets) |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    notes = [line for m, r in data.items() if m not in ("floor", *NO_RENDER)
             for line in stale_note(m, r.get("model"), "geometry", ignore=VIEW_CAP)]  # K = 3
    notes += [f"> **Older pipeline:** the {m} row was measured before the one mesh pipeline (commit "
              f"`{r['synth']['provenance'].get('commit', '?')}`; the pipeline was unified in e797ba0); it does "
              f"not compare with the other rows until `python -m bench geometry --models {m}` re-runs it.\n"
              for m, r in data.items() if not current(r)]
    notes += [f"> **Whole scene:** the {m} row was meshed without the object masks (ground and backdrop kept, "
              "scored against the whole exact mesh); the section's protocol is objects only.\n"
              for m, r in data.items() if current(r) and not r["synth"].get("mesh_masks")]
    if notes:
        out[2:2] = notes
    means = {m: r["synth"]["means"].get("synth", {}).get("3", {}) for m, r in data.items()}
    names = [s["name"] for s in first["synth"]["scenes"]]
    per = {m: {s["name"]: s["settings"].get("3", {}).get("geometry", {}) for s in r["synth"]["scenes"]}
           for m, r in data.items()}
    for m, mean in means.items():
        g = mean.get("geometry", {})
        psnr = "–" if m in NO_RENDER else num(mean.get("psnr"), 2)
        cells = [finite_mean(per[m], k, scale) for k, scale in (("chamfer", 1), ("accuracy", 1), ("completeness", 1),
                                                                   ("chamfer_rel", 100))]
        cells[3] = cells[3].replace(" (", " % (", 1) if "(" in cells[3] else cells[3] + (" %" if cells[3] != "–" else "")
        beyond = scene_mean(per[m], "completeness_dropped", 1.0)
        out.append(f"| {m} | " + " | ".join(cells) + f" | {num(None if beyond is None else 100 * beyond, 1)}"
                   + (" %" if beyond is not None else "") + f" | {num(scene_mean(per[m], 'fscore', 0.0), 3)} | "
                   f"{num(scene_mean(per[m], 'mask_iou', 0.0), 3)} | {num(mean.get('depth_abs_rel'))} | "
                   f"{num(g.get('seconds'), 1)} | {psnr} |")
    out += ["", "Per scene, Chamfer / extent (%), and the fraction of source-view pixels the depth source gave a depth "
            "(stereo: only pairs whose optical axes are within 60° match, so a view with no such neighbour among the 3 "
            "gets none):", "", "| scene | " + " | ".join(data) + " | stereo depth coverage |",
            "|---|" + "---|" * (len(data) + 1)]
    for n in names:
        cover = per.get("stereo", {}).get(n, {}).get("valid_depth_fraction")
        out.append(f"| {n} | " + " | ".join(num(100 * per[m].get(n, {}).get("chamfer_rel", float("nan")), 2)
                                             for m in data) + f" | {num(None if cover is None else 100 * cover, 1)} % |")
    out += ["", *goal_lines(means, per, names, data)]
    out += dtu_table(data)
    out += cpu_table(data, results)
    out.append("")
    for m, r in data.items():
        out += [f"{m}: " + prov(r["synth"]["provenance"]), ""]
    return "\n".join(out)


def finite_mean(rows: dict[str, dict], key: str, scale: float = 1.0) -> str:
    """Mean of ``key`` over the scenes where it is finite (Chamfer is inf with no surface within the cap),
    marked ``(n/N)`` when some are not; ``–`` when none has it."""
    if not any(key in r for r in rows.values()):
        return "–"
    values = [r.get(key) for r in rows.values()]  # None: no mesh in that scene
    finite = [float(v) for v in values if v is not None and not isinstance(v, str) and math.isfinite(v)]
    if not finite:
        return "inf"
    digits = 2 if scale != 1 else 4
    text = f"{scale * sum(finite) / len(finite):.{digits}f}"
    return text if len(finite) == len(values) else f"{text} ({len(finite)}/{len(values)})"


def scene_mean(rows: dict[str, dict], key: str, empty: float) -> float | None:
    """Mean of ``key`` over every scene, a scene without a mesh counting ``empty`` (F-score and IoU 0, all of
    the ground truth beyond the cap); ``None`` when no scene has it."""
    if not any(key in r for r in rows.values()):
        return None
    return sum(float(r[key]) if key in r else empty for r in rows.values()) / len(rows)


def current(r: dict) -> bool:
    """Measured by the one mesh pipeline (its settings recorded)."""
    return "mesh_options" in r["synth"]


def goal_lines(means: dict, per: dict, names: list[str], data: dict) -> list[str]:
    goals = []
    if "omnirecon-tiny" in means and "ibrnet-tiny" in means and not all(
            current(data[m]) and data[m]["synth"].get("mesh_masks") for m in ("omnirecon-tiny", "ibrnet-tiny")):
        goals.append("- Goal omnirecon-tiny Chamfer <= 0.7 x the IBRNet-density mesh's: not scored until both rows "
                     "are measured by the same pipeline and protocol.")
    elif "omnirecon-tiny" in means and "ibrnet-tiny" in means:
        o, i = means["omnirecon-tiny"].get("geometry", {}), means["ibrnet-tiny"].get("geometry", {})
        if o.get("chamfer") and i.get("chamfer"):
            ratio = o["chamfer"] / i["chamfer"]
            goals.append(f"- Goal omnirecon-tiny Chamfer <= 0.7 x the IBRNet-density mesh's: measured "
                         f"{ratio:.2f} x ({'met' if ratio <= 0.7 else 'not met'}).")
            wins = sum(per["omnirecon-tiny"].get(n, {}).get("chamfer", 1e9) < per["ibrnet-tiny"].get(n, {}).get(
                "chamfer", 1e9) for n in names)
            goals.append(f"- omnirecon-tiny has the lower Chamfer on {wins} of {len(names)} scenes.")
    for m in means:
        rel = finite_mean(per[m], "chamfer_rel", 100)
        if rel not in ("–", "inf"):
            value = float(rel.split()[0])
            goals.append(f"- Goal Chamfer <= 1 % of the extent, {m}: {rel.replace(' (', ' % (', 1) if '(' in rel else rel + ' %'}"
                         f" ({'met' if value <= 1.0 else 'not met'}"
                         + ("; over the scenes with a surface only" if "(" in rel else "") + ").")
    scored = [m for m in means if scene_mean(per[m], "fscore", 0.0) is not None and current(data[m])
              and data[m]["synth"].get("mesh_masks") == data.get("stereo", {}).get("synth", {}).get("mesh_masks")]
    if "stereo" in scored and len(scored) > 1:
        best = max(scored, key=lambda m: scene_mean(per[m], "fscore", 0.0))
        f_st, iou_st = scene_mean(per["stereo"], "fscore", 0.0), scene_mean(per["stereo"], "mask_iou", 0.0)
        empty = sum("faces" not in r for r in per["stereo"].values())
        goals.append(f"- Classical stereo from the same 3 views (the seed's DTU table lists COLMAP's classical MVS as "
                     f"the best Chamfer at 3 views): F-score {f_st:.3f}, silhouette IoU {iou_st:.3f}, no mesh in "
                     f"{empty} of {len(per['stereo'])} scenes; the best F-score here is **{best}**'s "
                     f"({scene_mean(per[best], 'fscore', 0.0):.3f}).")
    return goals


def dtu_table(data: dict) -> list[str]:
    dtu_models = [m for m, r in data.items() if r.get("dtu")]
    if not dtu_models:
        return []
    out = ["", "**DTU, sources 23 24 33** (8 held-out targets: PSNR of the model's render and the mesh silhouette's "
           "IoU against their masks; no DTU ground-truth point cloud here, so no Chamfer in mm to set beside the "
           "seed's):", "",
           "| scene | row | PSNR | PSNR masked | silhouette IoU | images -> mesh (s) | mesh faces | picture |",
           "|---|---|---|---|---|---|---|---|"]
    for s_name in [s["name"] for s in data[dtu_models[0]]["dtu"]["scenes"]]:
        for m in dtu_models:
            s = next((x for x in data[m]["dtu"]["scenes"] if x["name"] == s_name), None)
            if s is None:
                continue
            st = s["settings"].get("3", {})
            g, mean = st.get("geometry", {}), st.get("mean", {})
            pic = data[m].get("pictures", {}).get(s_name)
            psnr = ("–", "–") if m in NO_RENDER else (num(mean.get("psnr"), 2), num(mean.get("psnr_masked"), 2))
            out.append(f"| {s_name} | {m} | {psnr[0]} | {psnr[1]} | {num(g.get('mask_iou'), 3)} | "
                       f"{num(g.get('seconds'), 1)} | {g.get('faces', '–')} | "
                       + (f"[mesh](bench/results/{pic})" if pic else "–") + " |")
    if "stereo" in dtu_models:
        out.append("")
        for s_name in [x["name"] for x in data["stereo"]["dtu"]["scenes"]]:
            iou = {m: next((x["settings"].get("3", {}).get("geometry", {}).get("mask_iou") for x in data[m]["dtu"]["scenes"]
                            if x["name"] == s_name), None) for m in dtu_models
                   if current(data[m]) and data[m]["dtu"].get("mesh_masks") == data["stereo"]["dtu"].get("mesh_masks")}
            iou = {m: v for m, v in iou.items() if v is not None}
            if len(iou) > 1:
                best = max(iou, key=iou.get)
                out.append(f"- {s_name}: the highest silhouette IoU among the rows of the current pipeline and "
                           f"protocol is **{best}**'s ({iou[best]:.3f}); stereo {iou.get('stereo', float('nan')):.3f}.")
    pics = [(m, n, p) for m in dtu_models for n, p in data[m].get("pictures", {}).items()]
    if pics:
        out += ["", " ".join(f"![{m} {n}](bench/results/{p})" for m, n, p in pics if "scan24" in n), "",
                " ".join(f"![{m} {n}](bench/results/{p})" for m, n, p in pics if "scan24" not in n),
                "", "Pictures: the meshes seen from source view 23 (flat shading), left to right: "
                + ", ".join(m for m in dtu_models if data[m].get("pictures")) + "."]
    return out


def cpu_table(data: dict, results: Path) -> list[str]:
    rows = [(m, r["cpu_seconds"]) for m, r in data.items() if r.get("cpu_seconds")]
    if not rows:
        return []
    ab, ab_note = {}, ""
    if (results / "geometry_speed.json").is_file():
        speed = json.loads((results / "geometry_speed.json").read_text())
        ab, ab_note = speed.get("rows", {}), speed.get("note", "")
    out = ["", "**Where each row's CPU time goes** (process CPU seconds, 1 thread, the whole row: 10 procedural "
           "scenes + 2 DTU scans): target renders = the model's volumetric render of the held-out views (PSNR); "
           "depth = the depth source at the 3 source views; mesh = fusion to completion; score = Chamfer, "
           "silhouettes, depth errors; write = mesh files and the DTU pictures; other = loading, scene preparation, "
           "image scores.", "", "| row | " + " | ".join(PARTS) + " |", "|---|" + "---|" * len(PARTS)]
    for m, c in rows:
        out.append(f"| {m} | " + " | ".join(num(c.get(p), 0) for p in PARTS) + " |")
    if ab:
        out += ["", "Saved by this section's speed changes (`python -m bench geometry --speed-ab --models ...`, old and "
                "new side by side on the kept procedural meshes, identical numbers checked): "
                + "; ".join(f"{m}: pictures of the procedural meshes (no longer drawn: the section shows only DTU's) "
                            f"{t['picture']:.1f} CPU-s, Chamfer search {t['chamfer_unbounded']:.1f} -> "
                            f"{t['chamfer_bounded']:.1f} CPU-s (bounded at the cap)" for m, t in ab.items())
                + (f" ({ab_note})" if ab_note else "") + "."]
    return out
