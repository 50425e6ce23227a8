"""BENCHMARKS.md section: Lifting 2-D predictions into 3-D (`python -m bench lift`, `python -m bench lift_extra`)."""

from __future__ import annotations

import json
from pathlib import Path

from bench.report.common import VIEW_CAP, prov, stale_note


def section(results: Path) -> str | None:
    main_f, extra_f = results / "lift.json", results / "lift_extra.json"
    if not main_f.is_file():
        return None
    r = json.loads(main_f.read_text())
    out = ["## Lifting 2-D predictions into 3-D (`python -m bench lift`, `python -m bench lift_extra`)", "",
           f"Predict-then-blend (the predictor on the {r['num_views']} source views, its maps blended into the target "
           "with the model's own colour weights) against render-then-predict (the predictor on the rendered image), on "
           f"{len(r['scenes'])} held-out procedural scenes, `{r['protocol_set']}` protocol set. Oracle / noisy labels "
           f"are the scenes' ground-truth labels (noisy: {100 * r['noise']:.0f} % of each source view's pixels set to a "
           "wrong class); k-NN labels are a pixel classifier fitted on 6 labelled views that are no target's source "
           "(the semantic comparison: an oracle cannot run on a render); edge and keypoint references are the same "
           "predictor on the true target image. mIoU in %.", ""]
    for m, mr in r["models"].items():
        out += stale_note(m, mr.get("checkpoint"), "lift", ignore=VIEW_CAP)  # K = 3
    out += lift_table(r)
    models = list(r["models"])
    gains = []
    for m in models:
        k = r["models"][m]["means"].get("knn-labels", {})
        if k.get("lift") and k.get("render"):
            gains.append(f"{m} {k['lift']['miou'] - k['render']['miou']:+.1f}")
    if gains:
        out += ["", "Goal predict-then-blend >= render-then-predict + 10 mIoU (k-NN labels): " + ", ".join(gains) + "."]
    figs = [m for m in models if (results / "figures" / f"lift_{m}.png").is_file()]
    if figs:
        out += ["", " ".join(f"![lift {m}](bench/results/figures/lift_{m}.png)" for m in figs)]
    out += ["", prov(r["provenance"]) + (f" (rows of {', '.join(r['kept_from'])} from an earlier run of the same "
                                          "script)" if r.get("kept_from") else ""), ""]
    if extra_f.is_file():
        e = json.loads(extra_f.read_text())
        out += [f"Mesh path, tuning and embeddings (`python -m bench lift_extra`, {e.get('checkpoint', {}).get('path', '')}, "
                f"{len(e['scenes'])} scenes): the volumetric path against the mesh path (one surface point per pixel) "
                "with the exact mesh and with the model's own baked mesh; LoRA / bias-only tuning of the appearance "
                "branch with a leave-one-out semantic cross-entropy on 6 labelled views of the same scene; HED VGG "
                "features lifted as embeddings and classified by cosine similarity to label prototypes.", ""]
        ck = e.get("checkpoint") or {}
        out += stale_note(ck.get("preset") or "omnirecon-tiny", ck, "lift_extra", ignore=VIEW_CAP)  # K = 3
        out += extra_table(e)
        edits = sorted((results / "figures").glob("lift_edit_*.png"))
        if edits:
            out += ["", " ".join(f"![{p.stem}](bench/results/figures/{p.name})" for p in edits),
                    "", "Edits: recolour and remove an object by its lifted label (re-blended novel view), and delete "
                    "its faces from the baked mesh."]
        out += ["", prov(e["provenance"]), ""]
    return "\n".join(out)


def lift_table(result: dict) -> list[str]:
    """A Markdown table: one row per (model, task)."""
    lines = ["| model | task | metric | predict-then-blend | render-then-predict | 2-D input |", "|---|---|---|---|---|---|"]
    tasks = [("oracle-labels", "miou"), ("noisy-labels", "miou"), ("knn-labels", "miou"), ("sobel", "l1"),
             ("sobel", "fscore"), ("sobel", "fscore_labels"), ("canny", "l1"), ("canny", "fscore"),
             ("canny", "fscore_labels"), ("hed", "l1"), ("hed", "fscore"), ("hed", "fscore_labels"), ("harris", "l1"), ("harris", "fscore"), ("oracle-normals", "angle_deg")]
    for name, r in result["models"].items():
        for task, metric in tasks:
            if task not in r["means"]:
                continue
            m = r["means"][task]

            def get(part):
                v = (m.get(part) or {}).get(metric)
                return "-" if v is None else f"{v:.2f}" if metric in ("miou", "angle_deg") else f"{v:.4f}"

            lines.append(f"| {name} | {task} | {metric} | {get('lift')} | {get('render')} | {get('input')} |")
    return lines


def extra_table(result: dict) -> list[str]:
    """Markdown tables: the mesh path vs the volumetric path, then the tuning modes."""
    m = result["means"]
    lines = ["| measurement | volumetric | mesh (exact mesh) | mesh (exact, no occlusion test) | mesh (baked mesh) |",
             "|---|---|---|---|---|"]
    for key, label in (("oracle", "oracle labels lifted, mIoU"), ("knn", "knn labels lifted, mIoU"),
                       ("knn_render_then_predict", "knn render-then-predict, mIoU")):
        lines.append(f"| {label} | {m['volumetric'][key]:.2f} | {m['mesh_gt'][key]:.2f} | {m['mesh_gt_novis'][key]:.2f} | "
                     f"{m['mesh_model'][key]:.2f} |")
    lines.append(f"| knn on the true target image, mIoU | {m['knn_input']:.2f} | | | |")
    if "embedding" in m:
        e = m["embedding"]
        lines.append(f"| HED-feature cosine classification, mIoU (input {e['input']:.2f}, render-then-predict "
                     f"{e['render_then_predict']:.2f}) | {e['volumetric']:.2f} | {e['mesh_gt']:.2f} | | |")
    lines += ["", "| PET mode | tuned params | mIoU before | after | gain | gain per 1k params |", "|---|---|---|---|---|---|"]
    for mode, p in result["pet_means"].items():
        lines.append(f"| {mode} | {p['params']} | {p['before']:.2f} | {p['after']:.2f} | {p['gain']:+.2f} | "
                     f"{p['gain_per_1k_params']:+.3f} |")
    return lines
