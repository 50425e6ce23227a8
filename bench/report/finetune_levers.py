"""BENCHMARKS.md section: What fine-tuning tunes, and its ceiling (`python -m bench finetune_levers`,
`python -m bench finetune_ceiling`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import prov, read

LABELS = {"base": "encoder + appearance, 2048 px/step, fp32 (before)",
          "rays8k": "encoder + appearance, 8192 px/step", "bf16": "encoder + appearance, 8192 px/step, bf16",
          "lr2e-3": "encoder + appearance, 8192 px/step, lr 2e-3", "appearance": "appearance branch only, 8192 px/step",
          "encoder": "encoder only, 8192 px/step", "exposure": "encoder + appearance + exposure, 8192 px/step"}


def section(results: Path) -> str | None:
    """Held-out PSNR after 60 CPU-s per lever, and the best per-pixel blend (the most blend tuning can give)."""
    levers, ceiling = read(results, "finetune_levers.json"), read(results, "finetune_ceiling.json")
    if levers is None and ceiling is None:
        return None
    out = ["## What fine-tuning tunes, and how far it can go (`python -m bench finetune_levers`, "
           "`python -m bench finetune_ceiling`)", ""]
    if levers:
        out += ["`omnirecon finetune` for 60 CPU-seconds (1 thread, `--clock cpu`) per row, same mesh, sources, validation "
                "and held-out views, images at the photos' own resolution; held-out test PSNR in dB before -> after "
                "(objects: over the masks)."
                + ("" if all(r.get("visibility") for r in levers["rows"].values()) else
                   " Scored before `finetune`'s visibility test (every source blended at every point; it now blends "
                   "only the sources that see the point)."), "",
                "| scene | what is tuned | steps | whole image | objects | gain | load |", "|---|---|---:|---|---|---:|---:|"]
        for key, row in levers["rows"].items():
            b, a = row["before"], row["after"]
            obj = f"{b['psnr_masked']:.2f} -> {a['psnr_masked']:.2f}" if "psnr_masked" in b else "–"
            out.append(f"| {key.split('/')[0]} | {LABELS.get(row['row'], row['row'])} | {row['steps']} | "
                       f"{b['psnr']:.2f} -> {a['psnr']:.2f} | {obj} | {row['gain_db']:+.2f} | {row['load_average']:.0f} |")
        curves = read(results, "finetune_curves.json") or {"rows": {}}
        scenes = {key.split("/")[0] for key in levers["rows"]}
        for name, row in curves["rows"].items():  # the default's row: the curve's 60 s point (same settings)
            at = {c["seconds"]: c for c in row["curve"]}
            if name in scenes and 60.0 in at and row.get("rays") == 8192 and row.get("precision") == "fp32":
                b, a = row["curve"][0], at[60.0]
                obj = f"{b['psnr_masked']:.2f} -> {a['psnr_masked']:.2f}" if "psnr_masked" in b else "–"
                out.append(f"| {name} | {LABELS['rays8k']} (the default; the curve's 60 s point) | {a['steps']} | "
                           f"{b['psnr']:.2f} -> {a['psnr']:.2f} | {obj} | {a['psnr'] - b['psnr']:+.2f} | "
                           f"{row['load_average']:.0f} |")
        out += ["", prov(levers["provenance"]), ""]
    if ceiling:
        out += ["The ceiling: the mesh path colours a pixel with a convex blend of the source colours where its surface "
                "point projects, and tuning the encoder or the appearance branch only changes the blend weights. The "
                "best blend per pixel, chosen with the ground truth in hand, bounds every such lever on that mesh and "
                "those sources (same held-out views; PSNR over a fixed random subset of pixels per view).", "",
                "| scene | pretrained: whole image | ceiling | objects: pretrained | ceiling |", "|---|---:|---:|---:|---:|"]
        for name, row in ceiling["rows"].items():
            m, c = row["model"], row["ceiling"]
            obj = (f"{m['psnr_masked']:.2f} | {c['psnr_masked']:.2f} ({c['psnr_masked'] - m['psnr_masked']:+.2f})"
                   if "psnr_masked" in m else "– | –")
            out.append(f"| {name} | {m['psnr']:.2f} | {c['psnr']:.2f} ({c['psnr'] - m['psnr']:+.2f}) | {obj} |")
        out += ["", prov(ceiling["provenance"])]
    return "\n".join(out)
