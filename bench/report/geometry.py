"""BENCHMARKS.md section: Geometry from 3 source views (`python -m bench geometry`)."""

from __future__ import annotations

import json
from pathlib import Path

from bench.report.common import GEOMETRY_MODELS, num, prov, stale_note


def section(results: Path) -> str | None:
    data = {m: json.loads((results / f"geometry_{m}.json").read_text()) for m in GEOMETRY_MODELS
            if (results / f"geometry_{m}.json").is_file()}
    if not data:
        return None
    first = next(iter(data.values()))
    n_synth = len(first["synth"]["scenes"])
    out = ["## Geometry from 3 source views (`python -m bench geometry`)", "",
           "`omnirecon eval --geometry`, K = 3, `full` protocols (128-px long side). A mesh per scene by `omnirecon "
           "mesh`'s protocol (z-depth at the 3 virtually shifted source views, TSDF at 1/256 of the bounds diagonal, "
           "marching cubes, mask + visibility cleaning). Procedural: Chamfer distance (mean of accuracy and "
           "completeness, DTU-style sampling, outliers capped) against the exact mesh's observed object surface; "
           "`Chamfer / extent` divides by the diagonal of that surface's bounding box; F-score at 1 % of the bounds "
           f"diagonal; silhouette IoU on {first.get('synth_targets', 2)} held-out views per scene. Seconds: images "
           "to mesh (encode, render depth, fuse, marching cubes, clean) on this CPU, 1 thread.", "",
           f"**Held-out procedural scenes** (mean of {n_synth}; lengths in the generator's units):", "",
           "| model | Chamfer | accuracy | completeness | Chamfer / extent | F-score | silhouette IoU | "
           f"depth abs rel (targets) | images -> mesh (s) | PSNR ({first.get('synth_targets', 2)} targets) |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    notes = [line for m, r in data.items() if m != "floor" for line in stale_note(m, r.get("model"), "geometry")]
    if notes:
        out[2:2] = notes
    means = {m: r["synth"]["means"].get("synth", {}).get("3", {}) for m, r in data.items()}
    for m, mean in means.items():
        g = mean.get("geometry", {})
        out.append(f"| {m} | {num(g.get('chamfer'))} | {num(g.get('accuracy'))} | {num(g.get('completeness'))} | "
                   f"{num(100 * g['chamfer_rel'], 2) + ' %' if 'chamfer_rel' in g else '–'} | {num(g.get('fscore'), 3)} | "
                   f"{num(g.get('mask_iou'), 3)} | {num(mean.get('depth_abs_rel'))} | {num(g.get('seconds'), 1)} | "
                   f"{num(mean.get('psnr'), 2)} |")
    names = [s["name"] for s in first["synth"]["scenes"]]
    per = {m: {s["name"]: s["settings"].get("3", {}).get("geometry", {}) for s in r["synth"]["scenes"]}
           for m, r in data.items()}
    out += ["", "Per scene, Chamfer / extent (%):", "", "| scene | " + " | ".join(data) + " |",
            "|---|" + "---|" * len(data)]
    for n in names:
        out.append(f"| {n} | " + " | ".join(num(100 * per[m].get(n, {}).get("chamfer_rel", float("nan")), 2)
                                             for m in data) + " |")
    goals = []
    if "omnirecon-tiny" in means and "ibrnet-tiny" in means:
        o, i = means["omnirecon-tiny"].get("geometry", {}), means["ibrnet-tiny"].get("geometry", {})
        if o.get("chamfer") and i.get("chamfer"):
            ratio = o["chamfer"] / i["chamfer"]
            goals.append(f"- Goal omnirecon-tiny Chamfer <= 0.7 x the IBRNet-density mesh's: measured "
                         f"{ratio:.2f} x ({'met' if ratio <= 0.7 else 'not met'}).")
            wins = sum(per["omnirecon-tiny"].get(n, {}).get("chamfer", 1e9) < per["ibrnet-tiny"].get(n, {}).get(
                "chamfer", 1e9) for n in names)
            goals.append(f"- omnirecon-tiny has the lower Chamfer on {wins} of {len(names)} scenes.")
    for m, mean in means.items():
        g = mean.get("geometry", {})
        if "chamfer_rel" in g:
            goals.append(f"- Goal Chamfer <= 1 % of the extent, {m}: {100 * g['chamfer_rel']:.2f} % "
                         f"({'met' if g['chamfer_rel'] <= 0.01 else 'not met'}).")
    out += ["", *goals]
    dtu_models = [m for m, r in data.items() if r.get("dtu")]
    if dtu_models:
        out += ["", "**DTU, sources 23 24 33** (8 held-out targets: PSNR and the mesh silhouette's IoU against their "
                "masks; no DTU ground-truth point cloud here):", "",
                "| scene | model | PSNR | PSNR masked | silhouette IoU | images -> mesh (s) | mesh faces | picture |",
                "|---|---|---|---|---|---|---|---|"]
        for s_name in [s["name"] for s in data[dtu_models[0]]["dtu"]["scenes"]]:
            for m in dtu_models:
                s = next(x for x in data[m]["dtu"]["scenes"] if x["name"] == s_name)
                st = s["settings"].get("3", {})
                g, mean = st.get("geometry", {}), st.get("mean", {})
                pic = data[m].get("pictures", {}).get(s_name)
                out.append(f"| {s_name} | {m} | {num(mean.get('psnr'), 2)} | {num(mean.get('psnr_masked'), 2)} | "
                           f"{num(g.get('mask_iou'), 3)} | {num(g.get('seconds'), 1)} | {g.get('faces', '–')} | "
                           + (f"[mesh](bench/results/{pic})" if pic else "–") + " |")
        pics = [(m, n, p) for m in dtu_models for n, p in data[m].get("pictures", {}).items()]
        if pics:
            out += ["", " ".join(f"![{m} {n}](bench/results/{p})" for m, n, p in pics if "scan24" in n), "",
                    " ".join(f"![{m} {n}](bench/results/{p})" for m, n, p in pics if "scan24" not in n),
                    "", "Pictures: the meshes seen from source view 23 (flat shading), left to right: "
                    + ", ".join(dtu_models) + "."]
    out.append("")
    for m, r in data.items():
        out += [f"{m}: " + prov(r["synth"]["provenance"]), ""]
    return "\n".join(out)
