"""Lifting, part 2, measured with ``checkpoints/omnirecon-tiny``: the mesh path vs the volumetric path,
parameter-efficient tuning, the embedding path and the edits.

    python -m bench lift_extra            # 3 held-out procedural scenes (~10 CPU-minutes at 1 thread)
    python -m bench lift_extra --tiny     # one scene, one target, few steps (a smoke run)

Held-out procedural scenes (``synth:eval``, seeds 900000+) under the ``cpu`` protocol set (64 px, 2
targets per scene), K = 3 nearest pool views as sources. Per target:

* **label lifting** of ``oracle-labels`` (GT one-hot) and ``knn-labels`` (a k-NN pixel classifier fitted
  on 6 labelled pool views that are no target's source) on three paths: volumetric (ray weights), mesh
  with the scene's exact mesh (``mesh_gt``: the ceiling of the mesh path; ``mesh_gt_novis`` without the
  renderer's occlusion test, as in the paper) and mesh with the model's own baked mesh (``mesh_model``:
  ``omnirecon mesh``'s protocol from the K sources); mIoU (%) against the target's GT labels, and
  render-then-predict of ``knn-labels`` on each path's render;
* **embedding path**: HED VGG16 features (blocks 1-3, 448-d) of the sources, lifted (volumetric and
  exact-mesh path), classified by cosine similarity to per-class prototypes averaged from the sources'
  labelled pixels; vs the same classifier on the true target image (``input``) and on the volumetric
  render (render-then-predict).

Per scene: **PET** (LoRA r = 4, bias-only, full appearance branch as a reference), 40 Adam steps of 256
rays on the leave-one-out lift among 6 labelled pool views; mIoU of their GT labels lifted into the
targets before/after, and the gain per tuned parameter. On the first scene, the **edits** (recolour
and remove the largest object through both paths; delete its faces from the exact mesh, face labels
lifted from the 12 nearest pool views; the mesh path's remove renders the mesh without them) with one
picture per kind in ``bench/results/figures/lift_edit_*.png``.

Writes ``bench/results/lift_extra.json``.
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
K = 3
PET_MODES = (("lora", 4), ("bias", 0), ("full", 0))


def miou(probs, gt, C) -> float:
    from omnirecon.lift import metrics as M

    return 100 * M.iou_from_confusion(M.confusion(probs.argmax(-1) if probs.dim() == 3 else probs, gt, C))["miou"]


def mesh_renderer(model, mesh, scene, views, visibility=False):
    from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions
    from omnirecon.rays import Sources

    opts = MeshRenderOptions(background=tuple(scene.background), visibility=visibility, cull_back_faces=False)
    return MeshRenderer(model, mesh, Sources.from_scene(scene, views), opts)


def lift_target(model, scene, t, src, preds, table, hed, gt_mesh) -> dict:
    """Label and embedding lifting of one target on the three paths."""
    from omnirecon.lift import embed as EM
    from omnirecon.lift.blend import render_lifted, render_lifted_mesh
    from omnirecon.lift.predictors import labels_to_classes
    from omnirecon.mesh.build import mesh_from_model
    from omnirecon.rays import Sources

    C = len(table)
    gt = labels_to_classes(scene.labels[t], table)
    signals = {n: (p.predict_views(scene.images[src], src), p.kind) for n, p in preds.items()}
    queries = None
    if hed is not None:
        emb = hed.predict_views(scene.images[src])
        queries = EM.prototypes(emb, labels_to_classes(scene.labels[src], table), C)
        signals["hed"] = (emb, "embedding")
    row, seconds = {"target": t, "sources": src}, {}
    start = time.perf_counter()
    with torch.no_grad():
        feats = model.encode(Sources.from_scene(scene, src))
    vol = render_lifted(model, feats, scene.cameras[t], signals, chunk=512)
    seconds["volumetric"] = time.perf_counter() - start
    start = time.perf_counter()
    baked = mesh_from_model(model, scene, src).mesh
    seconds["bake"] = time.perf_counter() - start
    paths = {"volumetric": vol}
    for name, mesh, vis in (("mesh_gt", gt_mesh, True), ("mesh_gt_novis", gt_mesh, False), ("mesh_model", baked, True)):
        start = time.perf_counter()
        with mesh_renderer(model, mesh, scene, src, visibility=vis) as r:
            paths[name] = render_lifted_mesh(r, scene.cameras[t], signals)
        seconds[name] = time.perf_counter() - start
    knn = preds["knn-labels"]
    for name, lifted in paths.items():
        row[name] = {"oracle": miou(lifted.maps["oracle-labels"], gt, C), "knn": miou(lifted.maps["knn-labels"], gt, C),
                     "knn_render_then_predict": miou(knn(lifted.rgb), gt, C)}
    row["knn_input"] = miou(knn(scene.images[t]), gt, C)
    row["mesh_model_faces"] = len(baked.faces)
    if hed is not None:
        cls = lambda e: EM.classify(e, queries)  # noqa: E731
        row["embedding"] = {"volumetric": miou(cls(vol.maps["hed"]), gt, C),
                            "mesh_gt": miou(cls(paths["mesh_gt"].maps["hed"]), gt, C),
                            "input": miou(cls(hed(scene.images[t])), gt, C),
                            "render_then_predict": miou(cls(hed(vol.rgb)), gt, C)}
    row["seconds"] = seconds
    return row


def pet_scene(base, scene, targets, pool, table, steps: int) -> dict:
    from omnirecon.lift import tune as T

    labelled = [pool[i] for i in np.unique(np.linspace(0, len(pool) - 1, 6).round().astype(int))]
    before = T.lifted_miou(base, scene, targets, labelled, table, K)
    out = {"labelled": labelled, "before": before["miou"], "modes": {}}
    for mode, rank in PET_MODES:
        model = copy.deepcopy(base)
        start = time.perf_counter()
        views = T.labelled_views(model, scene, labelled, table, K)
        fit = T.tune(model, views, T.PETOptions(mode=mode, rank=max(rank, 1), steps=steps, rays=256, lr=1e-2))
        seconds = time.perf_counter() - start
        after = T.lifted_miou(model, scene, targets, labelled, table, K)["miou"]
        out["modes"][mode] = {"rank": rank or None, "params": fit["params"], "after": after,
                              "gain": after - before["miou"], "gain_per_1k_params": 1000 * (after - before["miou"]) /
                              fit["params"], "loss_first": fit["losses"][0], "loss_last": float(np.mean(fit["losses"][-5:])),
                              "tune_seconds": seconds}
    return out


def face_picture(mesh, colours, camera, background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Faces in their colours (head-light shaded) from ``camera``. ``# [H, W, 3]``"""
    from omnirecon.render.raster import MeshRasterizer

    with MeshRasterizer.from_trimesh(mesh, cull_back_faces=False) as rast:
        g = rast.rasterize(camera, normals="face")
    img = np.ones((camera.height, camera.width, 3)) * np.asarray(background)
    hit = g.face.numpy() >= 0
    _, d = camera.to(dtype=torch.float64).image_rays()
    lam = np.abs((g.normals.numpy().astype(np.float64) * d.reshape(camera.height, camera.width, 3).numpy()).sum(-1))
    img[hit] = colours[g.face.numpy()[hit]] * (0.35 + 0.65 * lam[hit])[:, None]
    return img


def edits(model, scene, targets, pool, table, gt_mesh, figures: Path) -> dict:
    """Recolour / remove the largest object of the first target through both paths (mesh path, remove: the
    object's faces deleted for the after view); delete its faces from the mesh (face labels lifted)."""
    import functools

    from omnirecon.data.io import write_image
    from omnirecon.engine.views import select_sources
    from omnirecon.lift import edit as E
    from omnirecon.lift import experiment as X
    from omnirecon.lift import tune as T
    from omnirecon.lift.predictors import labels_to_classes
    from omnirecon.lift.surface import face_maps, gt_face_labels, labels_from_probs
    from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions
    from omnirecon.rays import Sources

    t = targets[0]
    src = select_sources(scene, scene.cameras[t], pool, K)
    lab = scene.labels[t].numpy()
    label = int(np.bincount(lab.reshape(-1), minlength=256)[1:255].argmax()) + 1
    cls = int(np.searchsorted(table, label))
    out = {"target": t, "label": label}
    # geometry: face labels and colours lifted from the 12 pool views nearest the target; delete the object
    views = select_sources(scene, scene.cameras[t], pool, 12)
    maps, seen, known = face_maps(model, gt_mesh, Sources.from_scene(scene, views),
                                  {"labels": (T.one_hot_views(scene, views, table), "probabilities"),
                                   "rgb": (scene.images[views], "regression")})
    labels = labels_from_probs(gt_mesh, maps["labels"], seen)
    colours = np.where(known[:, None], maps["rgb"], 0.5)
    edited_mesh, edited_colours, keep = E.edit_faces(gt_mesh, colours, labels, cls, "remove")
    gtf = labels_to_classes(gt_face_labels(scene), table)
    area = np.asarray(gt_mesh.area_faces)
    out["mesh"] = {"faces": len(gt_mesh.faces), "deleted": len(gt_mesh.faces) - len(keep),
                   "gt_object_faces": int((gtf == cls).sum()), "deleted_correct": int(((labels == cls) & (gtf == cls)).sum()),
                   "face_label_accuracy": float((labels == gtf).mean()),
                   "face_label_accuracy_area": float((area * (labels == gtf)).sum() / area.sum()), "seen": float(seen.mean())}
    cam = scene.cameras[t]
    write_image(figures / "lift_edit_mesh.png", X.panel([face_picture(gt_mesh, colours, cam),
                                                         face_picture(gt_mesh, X.palette(len(table))[np.clip(labels, 0, None)], cam),
                                                         face_picture(edited_mesh, edited_colours, cam)]))
    images, onehot = scene.images[src], T.one_hot_views(scene, src, table)
    masks = scene.labels[src] == label
    opts = MeshRenderOptions(background=tuple(scene.background), visibility=True, cull_back_faces=False)
    for action, kw in (("recolour", {"colour": (0.1, 0.9, 0.2)}), ("remove", {"fill": "inpaint"})):
        edited = E.edit_images(images, masks, action, background=tuple(scene.background), **kw)
        with torch.no_grad():
            feats = model.encode(Sources.from_scene(scene, src))
            vol = E.reblend_volumetric(model, feats, scene.cameras[t], images, edited, onehot, chunk=1024)
        after = (functools.partial(MeshRenderer, model, edited_mesh, Sources.from_scene(scene, src), opts)
                 if action == "remove" else None)
        with MeshRenderer(model, gt_mesh, Sources.from_scene(scene, src), opts) as r:
            mesh = E.reblend_mesh(r, cam, images, edited, onehot, after)
        for name, res in (("volumetric", vol), ("mesh_gt", mesh)):
            obj = (res["labels"].argmax(-1) == cls).numpy()
            d = (res["after"] - res["before"]).abs().amax(-1).numpy()
            out[f"{action}_{name}"] = {"mean_change_object": float(d[obj].mean()), "mean_change_other": float(d[~obj].mean()),
                                       "changed_other_above_0.1": float((d[~obj] > 0.1).mean())}
        write_image(figures / f"lift_edit_{action}.png", X.panel(
            [scene.images[t].numpy(), edited[0].numpy(), vol["before"].clamp(0, 1).numpy(), vol["after"].clamp(0, 1).numpy(),
             mesh["before"].clamp(0, 1).numpy(), mesh["after"].clamp(0, 1).numpy()]))
    return out




def mean_of(rows, path):
    vals = []
    for r in rows:
        v = r
        for k in path:
            v = v.get(k) if isinstance(v, dict) else None
        if v is not None:
            vals.append(v)
    return float(np.mean(vals)) if vals else None


def _relative(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def main(argv: list[str] | None = None) -> None:
    from omnirecon.data.io import write_json
    from omnirecon.engine.checkpoint import fingerprint, load_checkpoint
    from omnirecon.engine.protocols import targets_and_pool
    from omnirecon.engine.scenes import prepare_scenes
    from omnirecon.engine.views import select_sources
    from omnirecon.lift import experiment as X
    from omnirecon.lift import predictors as P
    from omnirecon.lift.hed import available
    from omnirecon.mesh.geometry import ground_truth_mesh
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", type=Path, default=ROOT / "checkpoints" / "omnirecon-tiny")
    p.add_argument("--tiny", action="store_true", help="one scene, one target, 5 PET steps")
    p.add_argument("--scenes", type=int, default=3)
    p.add_argument("--steps", type=int, default=40, help="PET Adam steps")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    if not (a.ckpt / "meta.json").is_file():
        raise SystemExit(f"no checkpoint at {a.ckpt} (pass --ckpt)")
    model, meta = load_checkpoint(a.ckpt)
    model.eval()
    steps = 5 if a.tiny else a.steps
    scenes = prepare_scenes(["synth:eval"], 1 if a.tiny else a.scenes, cache=ROOT / "outputs" / "cache", protocol_set="cpu")
    hed = None
    if available() is None:
        from omnirecon.lift.embed import hed_features

        hed = hed_features()
    rows, pets, edit = [], [], None
    start = time.perf_counter()
    for si, es in enumerate(scenes):
        scene = es.scene
        targets, pool = targets_and_pool(es.protocol, scene)
        targets = targets[:1] if a.tiny else targets
        sources = {t: select_sources(scene, scene.cameras[t], pool, K) for t in targets}
        table = P.class_table(scene)
        train = X.knn_train_views(pool, {v for s in sources.values() for v in s})
        preds = {"oracle-labels": P.oracle_labels(scene, table), "knn-labels": P.knn_labels(scene, train, table=table)}
        gt_mesh = ground_truth_mesh(scene)
        for t in targets:
            rows.append({"scene": es.name, **lift_target(model, scene, t, sources[t], preds, table, hed, gt_mesh)})
            print(f"{es.name} target {t}: " + ", ".join(f"{k} oracle {rows[-1][k]['oracle']:.1f} knn {rows[-1][k]['knn']:.1f}"
                                                      for k in ("volumetric", "mesh_gt", "mesh_model")), flush=True)
        pets.append({"scene": es.name, **pet_scene(model, scene, targets, pool, table, steps)})
        print(f"{es.name} PET: before {pets[-1]['before']:.1f}, " + ", ".join(
            f"{m} {v['after']:.1f} ({v['params']} params)" for m, v in pets[-1]["modes"].items()), flush=True)
        if si == 0:
            edit = edits(model, scene, targets, pool, table, gt_mesh, a.out / "figures")
    means = {k: {m: mean_of(rows, (k, m)) for m in ("oracle", "knn", "knn_render_then_predict")}
             for k in ("volumetric", "mesh_gt", "mesh_gt_novis", "mesh_model")}
    means["knn_input"] = mean_of(rows, ("knn_input",))
    if hed is not None:
        means["embedding"] = {m: mean_of(rows, ("embedding", m)) for m in ("volumetric", "mesh_gt", "input", "render_then_predict")}
    pet_means = {}
    for mode, _ in PET_MODES:
        pm = {k: mean_of([r["modes"][mode] for r in pets], (k,)) for k in ("after", "gain", "gain_per_1k_params")}
        pm["params"] = pets[0]["modes"][mode]["params"]
        pm["before"] = mean_of(pets, ("before",))
        pet_means[mode] = pm
    result = {"provenance": provenance(seed=0, threads=a.threads), "mode": "tiny" if a.tiny else "full",
              "checkpoint": {**fingerprint(a.ckpt), "path": _relative(a.ckpt)}, "scenes": [s.name for s in scenes],
              "protocol_set": "cpu", "num_views": K, "pet_steps": steps, "hed_features": None if hed is None else hed.description,
              "means": means, "pet_means": pet_means, "targets": rows, "pet": pets, "edits": edit,
              "edit_figures": {"lift_edit_recolour.png / lift_edit_remove.png": "true target | first edited source | "
                               "volumetric before | after | exact-mesh before | after",
                               "lift_edit_mesh.png": "lifted face colours | lifted face labels | object's faces deleted "
                               "(exact mesh, target camera)"},
              "seconds": time.perf_counter() - start}
    write_json(a.out / "lift_extra.json", result)
    print(f"{result['seconds']:.0f} s; wrote {a.out / 'lift_extra.json'}")

