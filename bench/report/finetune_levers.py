"""BENCHMARKS.md section: What fine-tuning tunes, and its ceiling (`python -m bench finetune_levers`,
`python -m bench finetune_ceiling`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import prov, read

LABELS = {"base": "encoder + appearance, 2048 px/step, fp32",
          "rays8k": "encoder + appearance, 8192 px/step", "bf16": "encoder + appearance, 8192 px/step, bf16",
          "lr2e-3": "encoder + appearance, 8192 px/step, lr 2e-3", "appearance": "appearance branch only, 8192 px/step",
          "encoder": "encoder only, 8192 px/step", "exposure": "encoder + appearance + exposure, 8192 px/step",
          "appearance_lr3e-3": "appearance branch only, 8192 px/step, lr 3e-3 (the default during session 13)",
          "appearance_exposure": "appearance + exposure, 8192 px/step, lr 3e-3",
          "mixed": "encoder + appearance, each step's pixels from every tuning view (`--step-views 0`)",
          "latest": "encoder + appearance, no validation: the state at the end (diagnostic)",
          "mixed_latest": "`--step-views 0`, no validation: the state at the end (diagnostic)",
          "mixed_lr2e-4": "`--step-views 0`, lr 2e-4",
          "uniform": "encoder + appearance, `--objects 0` (pixels uniform over the shaded ones)",
          "uniform_exposure": "encoder + appearance + exposure, `--objects 0`",
          "mixed_uniform": "`--step-views 0 --objects 0`",
          "mixed_uniform_latest": "`--step-views 0 --objects 0`, no validation: the state at the end (diagnostic)",
          "skip1": "encoder + appearance, tuning views skip their nearest source (`--skip-nearest 1`)",
          "skip2": "encoder + appearance, `--skip-nearest 2`",
          "skip1_latest": "`--skip-nearest 1`, no validation: the state at the end (diagnostic)",
          "residual": "a 3-D residual colour grid only (`--tune residual`, 16³, lr 1e-2; the blend fixed)",
          "residual_latest": "`--tune residual`, no validation: the state at the end (diagnostic)",
          "residual_uniform": "`--tune residual --objects 0`",
          "residual_uniform_latest": "`--tune residual --objects 0`, no validation: the state at the end (diagnostic)"}
BEFORE = " *(before the visibility test, older mesh)*"
"""Marks a row measured before ``finetune``'s visibility test (on an older mesh: not comparable with the others)."""


def sources(row: dict) -> str:
    """Which sources a row blended: each pixel's nearest (``finetune``'s default since session 14) or fixed ones."""
    return f"nearest {row['nearest']}" if row.get("nearest") else "3 fixed"


def commit(row: dict) -> str:
    """The commit a row ran at (its own provenance; ``~`` when recovered from the file's history: that commit or an
    earlier one), ``?`` when unknown."""
    p = row.get("provenance") or {}
    return f"{'~' if p.get('recovered') else ''}`{p['commit']}`" if p.get("commit") else "?"


def section(results: Path) -> str | None:
    """Held-out PSNR after 60 CPU-s per lever, and the best per-pixel blend (the most blend tuning can give)."""
    levers, ceiling = read(results, "finetune_levers.json"), read(results, "finetune_ceiling.json")
    if levers is None and ceiling is None:
        return None
    out = ["## What fine-tuning tunes, and how far it can go (`python -m bench finetune_levers`, "
           "`python -m bench finetune_ceiling`)", ""]
    if levers:
        out += ["`omnirecon finetune` for 60 CPU-seconds (1 thread, `--clock cpu`) per row, the same held-out views; "
                "`nearest 6` rows: today's defaults and the Fine-tuning curves row's mesh; `3 fixed` rows: the 3 fixed "
                "sources and the older mesh they were measured with (session 13); images at the photos' own resolution; held-out test PSNR in dB before -> after "
                "(objects: over the masks); commit: the one each row ran at (`~`: recovered from the results file's history, "
                "that commit or an earlier one)."
                + ("" if all(r.get("visibility") for r in levers["rows"].values()) else
                   " Rows marked" + BEFORE + " were scored before `finetune`'s visibility test (every source blended "
                   "at every point; it now blends only the sources that see the point) on an older mesh; the others "
                   "with it, on the mesh of the Fine-tuning curves row."), "",
                "| scene | sources | what is tuned | steps | whole image | objects | gain | load | commit |",
                "|---|---|---|---:|---|---|---:|---:|---|"]
        for key, row in levers["rows"].items():
            b, a = row["before"], row["after"]
            obj = f"{b['psnr_masked']:.2f} -> {a['psnr_masked']:.2f}" if "psnr_masked" in b else "–"
            label = LABELS.get(row["row"], row["row"]) + ("" if row.get("visibility") else BEFORE)
            if a.get("seconds", 60.0) != 60.0:  # e.g. the demo scene at `make demo`'s 30 s
                label += f" *({a['seconds']:g} CPU-s)*"
            out.append(f"| {key.split('/')[0]} | {sources(row)} | {label} | {row['steps']} | "
                       f"{b['psnr']:.2f} -> {a['psnr']:.2f} | {obj} | {row['gain_db']:+.2f} | {row['load_average']:.0f} | "
                       f"{commit(row)} |")
        curves = read(results, "finetune_curves.json") or {"rows": {}}
        meshes = {(key.split("/")[0], row["mesh"]) for key, row in levers["rows"].items() if row.get("visibility")}
        for name, row in curves["rows"].items():  # the default's row: the curve's 60 s point (same settings and mesh)
            at = {c["seconds"]: c for c in row["curve"]}
            if (name, row["mesh"]) in meshes and 60.0 in at and row.get("rays") == 8192 and row.get("precision") == "fp32":
                b, a = row["curve"][0], at[60.0]
                obj = f"{b['psnr_masked']:.2f} -> {a['psnr_masked']:.2f}" if "psnr_masked" in b else "–"
                what = " + ".join(row["tuned"]) + (f", lr {row['lr']:g}" if "lr" in row else "")
                out.append(f"| {name} | {sources(row)} | {what}, 8192 px/step (the default; the curve's 60 s point) | {a['steps']} | "
                           f"{b['psnr']:.2f} -> {a['psnr']:.2f} | {obj} | {a['psnr'] - b['psnr']:+.2f} | "
                           f"{row['load_average']:.0f} | {commit(row)} |")
        out += ["", prov(levers["provenance"]), ""]
    if ceiling:
        out += ["The ceiling: the mesh path colours a pixel with a convex blend of the source colours where its surface "
                "point projects, and tuning the encoder or the appearance branch only changes the blend weights. The "
                "best blend per pixel, chosen with the ground truth in hand, bounds every such lever on that mesh and "
                "those sources (same held-out views; PSNR over a fixed random subset of pixels per view). With the "
                "visibility test (`finetune`'s default) the model and the ceiling blend only the sources that see the "
                "point (with `nearest 6`: only the 6 nearest of those); *all sources*: the best blend over every source the "
                "point projects into, occluded and farther ones too (what those limits give up). Rows without it were measured before the test, on older meshes.", "",
                "| scene | sources | visibility test | pretrained: whole image | ceiling | all sources | objects: pretrained | "
                "ceiling | all sources |", "|---|---|---|---:|---:|---:|---:|---:|---:|"]
        for name, row in ceiling["rows"].items():
            m, c, a = row["model"], row["ceiling"], row.get("ceiling_all", {})
            def cell(d: dict, k: str) -> str:
                return f"{d[k]:.2f} ({d[k] - m[k]:+.2f})" if k in d else "–"
            obj = (f"{m['psnr_masked']:.2f} | {cell(c, 'psnr_masked')} | {cell(a, 'psnr_masked')}"
                   if "psnr_masked" in m else "– | – | –")
            vis = "yes" if row.get("visibility") else "no (before the test)"
            out.append(f"| {name} | {sources(row)} | {vis} | {m['psnr']:.2f} | {cell(c, 'psnr')} | {cell(a, 'psnr')} | {obj} |")
        out += ["", prov(ceiling["provenance"])]
    return "\n".join(out)
