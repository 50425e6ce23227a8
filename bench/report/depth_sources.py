"""BENCHMARKS.md section: Depth sources: whole image, coverage, geometry (`python -m bench depth_sources`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import missing, prov, read


def section(results: Path) -> str:
    """Depth source x scene through the mesh path (``python -m bench depth_sources``)."""
    r = read(results, "depth_sources.json")
    if r is None:
        return missing("depth_sources.json")
    def f(x, fmt="{:.2f}"):
        return "–" if x is None else fmt.format(x)

    out = ["## Depth sources: whole image, coverage, geometry (`python -m bench depth_sources`)", "", prov(r["provenance"]), "",
           "Meshes from the training views minus the held-out ones (DTU: 14 views, with the object masks) by the one "
           "mesh pipeline, scored like `omnirecon finetune --mesh M --clock cpu --threads 1` at the photos' resolution "
           "(fern 336x252, DTU 400x300, procedural 128 px). `learned`: omnirecon-tiny's coarse-pass depth at 128 px; "
           "`floor`: the plane sweep; `stereo`: classical stereo (OpenCV SGBM on sideways neighbour pairs rectified "
           "from the poses, vote over 4 pairs); `+fill`: completion (every content pixel of every meshed view covered, "
           f"backdrop on forward-facing scenes); `oracle`: exact depth. Rows marked tuned got {r['tuning_seconds']:.0f} "
           "CPU-s of tuning. PSNR: whole image (DTU: over the object mask); covered: over the pixels the mesh covers; "
           "coverage: held-out pixels on the mesh (DTU: of the mask); mesh s: CPU seconds images -> mesh (1 thread). "
           "Goals: fern ≥ 24 dB whole image after tuning with coverage ≥ 99 %; DTU ≥ 22 dB over the mask, IoU ≥ 0.95; "
           "procedural: within 1 dB of the exact mesh before tuning.", "",
           "| scene | depth | PSNR before → after | covered before → after | coverage | IoU | Chamfer | F | faces | mesh s | picture |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in r["rows"]:
        ps = row.get("psnr_masked") or row["psnr"]
        cv = row.get("psnr_covered") or {}
        pic = f"![{row['scene']} {row['source']}](bench/results/{row['picture']})" if row.get("picture") else ""
        out.append(f"| {row['scene']} | {row['source']} | {f(ps['before'])} → {f(ps.get('after'))} | "
                   f"{f(cv.get('before'))} → {f(cv.get('after'))} | {f(row.get('coverage'), '{:.1%}')} | "
                   f"{f(row.get('silhouette_iou'), '{:.3f}')} | {f(row.get('chamfer_rel'), '{:.2%}')} | "
                   f"{f(row.get('fscore'), '{:.3f}')} | {f(row.get('faces'), '{:,}')} | "
                   f"{f(row.get('mesh_cpu_seconds'), '{:.0f}')} | {pic} |")
    return "\n".join(out)
