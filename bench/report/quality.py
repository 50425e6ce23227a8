"""BENCHMARKS.md section: Novel-view quality (`python -m bench quality`)."""

from __future__ import annotations

import json
from pathlib import Path

from bench.report.common import QUALITY_MODELS, prov, scene_rows, stale_note
from omnirecon.splits import EVAL_ONLY_SCENES


def section(results: Path) -> str | None:
    data = {m: json.loads((results / f"quality_{m}.json").read_text()) for m in QUALITY_MODELS
            if (results / f"quality_{m}.json").is_file()}
    if not data:
        return None
    models = list(data)
    rows = {m: scene_rows(r) for m, r in data.items()}
    names = list(dict.fromkeys(n for m in models for n in rows[m]))
    ks = sorted({k for m in models for n in rows[m] for k in rows[m][n]}, key=int)
    first = next(iter(data.values()))
    out = ["## Novel-view quality (`python -m bench quality`)", "",
           f"Protocol set `{first.get('protocol_set', 'full')}` of `omnirecon eval` (docs/evaluation.md): images at a "
           "64-px long side, targets and source pools fixed per dataset, K nearest sources. dtu_scan24, dtu_scan37 and "
           "fern are never trained on; fox and lego are training scenes (their rows measure fitting). GPNR's "
           "`aux` is its other head (`rgb_aux`): gpnr-tiny renders the blended source colours (`output=colors`), "
           "so its `aux` is the feature head.", ""]
    for m, r in data.items():
        if m != "floor":
            out += stale_note(m, r["model"], "quality")
    masked = [n for n in names if any("psnr_masked" in rows[m].get(n, {}).get(k, {}) for m in models for k in ks)]
    for metric, label in (("psnr", "PSNR (dB), whole image", ), ("psnr_masked", "PSNR (dB) over the object mask: the "
                                                                 "metric of the masked protocols (DTU, Blender)"),
                          ("ssim", "SSIM"), ("st_lpips_alex", "ST-LPIPS (alex; not LPIPS)")):
        cols = [(m, k) for m in models for k in ks]
        out += [f"**{label}**", "", "| scene | " + " | ".join(f"{m} K={k}" for m, k in cols) + " |",
                "|---|" + "---|" * len(cols)]
        for n in (masked if metric == "psnr_masked" else names):
            cells = []
            for m, k in cols:
                v = rows[m].get(n, {}).get(k, {}).get(metric)
                aux = rows[m].get(n, {}).get(k, {}).get(f"{metric}_aux")
                cells.append("–" if v is None else f"{v:.3f}" if not metric.startswith("psnr") else
                             f"{v:.2f}" + (f" (aux {aux:.2f})" if aux is not None else ""))
            out.append(f"| {n} | " + " | ".join(cells) + " |")
        out.append("")
    if "gpnr-tiny" in rows and "ibrnet-tiny" in rows:
        out += ["**Goal GPNR >= IBRNet + 1 dB** (PSNR difference gpnr-tiny minus ibrnet-tiny):", ""]
        for n in names:
            diffs = [f"K={k}: {rows['gpnr-tiny'][n][k]['psnr'] - rows['ibrnet-tiny'][n][k]['psnr']:+.2f}"
                     for k in ks if k in rows["gpnr-tiny"].get(n, {}) and k in rows["ibrnet-tiny"].get(n, {})]
            out.append(f"- {n}: " + ", ".join(diffs))
        out.append("")
    if "floor" in rows:
        out += ["**Against the non-learned floor** (whole-image PSNR above the plane-sweep floor, the headline metric "
                "of docs/evaluation.md; over the object mask in brackets for the masked protocols, DTU and Blender; "
                "negative = below it):", ""]
        for m in models:
            if m == "floor":
                continue
            diffs = []
            for n in names:
                for k in ks:
                    a, f = rows[m].get(n, {}).get(k), rows["floor"].get(n, {}).get(k)
                    if a is None or f is None:
                        continue
                    masked = f" (mask {a['psnr_masked'] - f['psnr_masked']:+.2f})" \
                        if "psnr_masked" in a and "psnr_masked" in f else ""
                    diffs.append(f"{n} K={k}: {a['psnr'] - f['psnr']:+.2f}{masked}")
            out.append(f"- {m}: " + "; ".join(diffs))
        held_out = [n for n in names if n.startswith("synth:eval") or n in EVAL_ONLY_SCENES]
        for key, what in (("psnr", f"Held-out scenes (synth:eval, {', '.join(sorted(EVAL_ONLY_SCENES))}) where a "
                                   "model is below the floor in whole-image PSNR:"),
                          ("psnr_masked", "The same for the masked held-out scenes (DTU) in PSNR over the object mask:")):
            out += ["", what, ""]
            for m in models:
                if m == "floor":
                    continue
                below = [f"{n} K={k}" for n in held_out for k in ks
                         if key in rows[m].get(n, {}).get(k, {}) and key in rows["floor"].get(n, {}).get(k, {})
                         and rows[m][n][k][key] < rows["floor"][n][k][key]]
                out.append(f"- {m}: " + (", ".join(below) if below else "none"))
        out.append("")
    for m, r in data.items():
        out.append(f"{m}: " + prov(r["provenance"]) + (f"; checkpoint `{r['model'].get('checkpoint')}` at step "
                                                       f"{r['model'].get('step')}" if r["model"].get("checkpoint") else ""))
        out.append("")
    return "\n".join(out)
