"""BENCHMARKS.md section: Lifting 2-D predictions into 3-D (`python -m bench lift`, `python -m bench lift_extra`)."""

from __future__ import annotations

import json
from pathlib import Path

from bench.report.common import prov, stale_note


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
        out += stale_note(m, mr.get("checkpoint"), "lift")
    out += r["table"]
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
        out += stale_note(ck.get("preset") or "omnirecon-tiny", ck, "lift_extra")
        out += e["table"]
        edits = sorted((results / "figures").glob("lift_edit_*.png"))
        if edits:
            out += ["", " ".join(f"![{p.stem}](bench/results/figures/{p.name})" for p in edits),
                    "", "Edits: recolour and remove an object by its lifted label (re-blended novel view), and delete "
                    "its faces from the baked mesh."]
        out += ["", prov(e["provenance"]), ""]
    return "\n".join(out)
