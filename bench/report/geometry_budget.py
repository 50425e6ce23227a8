"""BENCHMARKS.md section: Geometry error budget, stage by stage (`python -m bench geometry_budget`)."""

from __future__ import annotations

import json
from pathlib import Path

from bench.report.common import prov


def section(results: Path) -> str | None:
    """The stage-by-stage geometry error budget of ``python -m bench geometry_budget``."""
    f = results / "geometry_budget.json"
    if not f.is_file():
        return None
    r = json.loads(f.read_text())
    out = ["## Geometry error budget, stage by stage (`python -m bench geometry_budget`)", "", prov(r["provenance"]), "",
           f"Procedural scenes at {r['resolution']} px (`demo`: the demo's held-out scene, seed 900999). Depth from the "
           "exact mesh (`oracle`), the plane-sweep `floor` and `omnirecon-tiny`, at the 3 default source views (`k3`) "
           "or every training view (`all`, each map from its own 3 nearest views). `reference`: VolRecon's protocol "
           "as `omnirecon mesh` ran it before (shifted views, nearest-pixel TSDF at 1/256 of the diagonal, cleaned "
           "with the object masks, so the ground goes); `fit`: `omnirecon/mesh/fusion.py`, background kept. "
           "Chamfer over the extent of the observed exact surface and F-score at 1 % of the diagonal, against the "
           "whole exact mesh (ground included); PSNR: the mesh path's whole-image held-out PSNR (omnirecon-tiny's "
           "appearance branch, 3 sources, no tuning). Goal: the oracle's all-view mesh within "
           f"{r['oracle_tolerance_db']} dB of the exact mesh.", "",
           "| scene | depth | views | fusion | depth abs rel / δ<1.25 | stage | faces | Chamfer | F-score | PSNR (exact mesh) | s |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in r["rows"]:
        ex = r["exact"][row["scene"]]
        d = row.get("depth") or {}
        dtxt = f"{d['abs_rel']:.3f} / {d['delta1']:.3f}" if d else "–"
        secs = sum(row["seconds"].values()) + row["render_seconds"]
        for i, (stage, m) in enumerate(row["stages"].items()):
            first = i == 0
            out.append(f"| {row['scene'] if first else ''} | {row['source'] if first else ''} | "
                       f"{row['views'] if first else ''} | {row['pipeline'] if first else ''} | {dtxt if first else ''} | "
                       f"{stage.replace('_', ' ')} | {m['faces']:,} | {100 * m['chamfer_rel']:.2f} % | {m['fscore']:.3f} | "
                       f"{m['psnr']:.2f} ({ex['psnr']:.2f}) | {f'{secs:.0f}' if first else ''} |")
    return "\n".join(out)
