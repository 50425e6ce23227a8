"""``omnirecon edit``: recolour or remove one object consistently in novel views, and on the baked mesh.

Pick the object by label value (``--label``) or by a click (``--click X Y`` in ``--click-view``, read
from the label maps); edit its pixels in every source image (:mod:`omnirecon.lift.edit`); re-blend
every target before/after through the model (``--path volumetric`` or ``mesh``); with an Omni-Recon
checkpoint also label the mesh's faces by lifting the labels to their centroids, delete or recolour
that label's faces and export GLB. Writes per target ``<view>_before.png``, ``<view>_after.png``,
``<view>_mask.png`` (pixels whose lifted label is the object) and ``<view>_panel.png``; the edited
sources under ``sources/``; ``mesh_original.glb`` and ``mesh_edited.glb`` (input frame); ``edit.json``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np

from omnirecon.data.io import write_image, write_json
from omnirecon.engine.machine import CheckpointInput, ChunkConfig, load_model, set_threads
from omnirecon.engine.protocols import given_targets
from omnirecon.engine.scenes import prepare_scenes
from omnirecon.engine.views import select_sources
from omnirecon.errors import InputError
from omnirecon.lift import edit as E
from omnirecon.lift import experiment as X
from omnirecon.lift import predictors as P
from omnirecon.lift.blend import supports_lifting
from omnirecon.lift.experiment import knn_train_views
from omnirecon.lift.predictors import labels_to_classes
from omnirecon.lift.surface import face_maps, gt_face_labels, labels_from_probs, scene_mesh
from omnirecon.mesh.files import write_mesh
from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions
from omnirecon.models.omnirecon import OmniRecon
from omnirecon.options import OutFolder, ProtocolScenes, SourceViews, check_options
from omnirecon.provenance import provenance
from omnirecon.rays import Sources
from omnirecon.workflows.folder import FolderVerb, LiftedTargets


@dataclass
class EditConfig(ProtocolScenes, OutFolder, SourceViews, CheckpointInput, LiftedTargets, ChunkConfig, FolderVerb):
    """Recolour or remove an object (picked by label or click) in the source images, re-blend novel views
    before/after, and delete or recolour its faces on the baked mesh (GLB)."""

    action: Literal["recolour", "remove"] = "recolour"
    """recolour: new hue and saturation, shading kept; remove: background colour or inpainting."""
    label: int | None = None
    """Label value of the object (as in the scene's label maps: 1..254 objects, 255 ground)."""
    click: tuple[int, int] | None = None
    """Pick the object under pixel (x=column, y=row) of --click-view instead of --label."""
    click_view: int | None = None
    """View of --click (default: the first source of the first target)."""
    labels: Literal["oracle", "knn"] = "oracle"
    """Per-view label maps: oracle (the scene's ground truth) or knn (a 2-D pixel classifier fitted on
    labelled views that are no target's source)."""
    colour: tuple[float, float, float] = (0.9, 0.1, 0.8)
    """--action recolour: RGB in [0, 1] whose hue and saturation the object takes."""
    fill: Literal["background", "inpaint"] = "background"
    """--action remove: paint with the scene's background colour, or biharmonic inpainting."""
    dilation: int = 1
    """--action remove: grow the object's pixels by this many px first (anti-aliased rims)."""
    reencode: bool = False
    """Re-run the model on the edited sources (the paper's loop: new features and, volumetric, new
    geometry) instead of blending the edited images with the original weights."""
    geometry: bool = True
    """Also edit the mesh (face labels lifted at the centroids) and export GLBs (Omni-Recon only)."""
    face_views: int = 12
    """Views whose label maps and images are lifted to the mesh's faces: the sources plus the nearest pool
    views to the first target up to this many (faces hidden in every view take their neighbours' labels)."""

    command: ClassVar[str] = "edit"

    def default_out(self) -> Path:
        return Path("outputs/edit") / f"{Path(self.ckpt).name}_{self.action}"

    def run(self, folder: Path | None = None) -> list[str]:
        lines: list[str] = []
        check_options("edit", self)  # the numbers (omnirecon/options.py); here for callers other than the CLI
        if (self.label is None) == (self.click is None):
            raise InputError("give exactly one of --label or --click", None, "e.g. --label 2 or --click 30 20")
        set_threads(self.threads)
        model, info = load_model(self.ckpt, None, "cpu")
        if not supports_lifting(model):
            raise InputError(f"model {info['name']} cannot re-blend signals", self.ckpt,
                             "use an Omni-Recon, IBRNet or GPNR checkpoint")
        if (self.path == "mesh" or self.geometry) and not isinstance(model, OmniRecon):
            raise InputError(f"the mesh path and the mesh edit need Omni-Recon, got {info['name']}", self.ckpt,
                             "use an omnirecon checkpoint, or --path volumetric --no-geometry")
        out = self.out or self.default_out()
        folder = folder or out
        es = prepare_scenes([self.scene], 1, self.cache, protocol_set=self.protocol_set)[0]
        if es.scene.labels is None:
            raise InputError("the scene has no label maps", es.path, "use a procedural scene (synth:eval or "
                             "`omnirecon synth`)")
        result = {"model": info, **run_edit(self, model, es, folder / es.name)}

        write_json(folder / "edit.json", {"provenance": provenance(seed=0), **result})
        r = result
        lines.append(f"{r['action']} label {r['label']} in {len(r['edited_views'])} source views; "
              + ", ".join(f"view {t['target']}: mean change {t['mean_change_inside']:.3f} on the object's lifted pixels, "
                          f"{t['mean_change_outside']:.4f} elsewhere" for t in r["targets"]))
        if r.get("mesh"):
            m = r["mesh"]
            lines.append(f"mesh ({m['source']}): {m['faces_hit']} of {m['faces']} faces labelled {r['label']} "
                  f"{'deleted' if r['action'] == 'remove' else 'recoloured'}")
        lines.append(f"wrote {out / 'edit.json'} and pictures under {out}")
        return lines


def label_maps(cfg: EditConfig, scene, pool: list[int], used: set[int], table: np.ndarray, needed: list[int]):
    """Per-view label values ``# [N, H, W]`` from the ground truth or, for the ``needed`` views, the k-NN
    segmenter (fitted on pool views that are no target's source, ``used``; the other views keep their
    ground truth and must not be read)."""
    import torch

    if cfg.labels == "oracle":
        return scene.labels.clone()
    train = knn_train_views(pool, used)
    if not train:
        raise InputError("knn labels need labelled views that are no target's source", scene.path, "lower --num-views")
    knn = P.knn_labels(scene, train, table=table)
    out = scene.labels.clone()
    for v in sorted(set(needed)):
        out[v] = torch.from_numpy(table[knn(scene.images[v]).argmax(-1).numpy()])
    return out


def run_edit(cfg: EditConfig, model, es, folder: Path) -> dict:
    """The edit of one scene (see the module docstring); returns the JSON record."""
    scene = es.scene
    targets, pool, sources, face_views = _views(cfg, es)
    used = sorted({v for s in sources.values() for v in s})
    table = P.class_table(scene)
    labels = label_maps(cfg, scene, pool, set(used), table, used + face_views)  # [N, H, W] values
    target_label = _target_label(cfg, es, labels, sources[targets[0]], table)
    background = tuple(scene.background) if scene.background is not None else (1.0, 1.0, 1.0)
    edited = _edit_sources(cfg, scene, used, labels[used] == target_label, background, folder)
    onehot = _onehot(labels, table)
    cls = int(np.searchsorted(table, target_label))
    mesh_rec, meshes = None, None
    if cfg.path == "mesh" or cfg.geometry:
        mesh_rec = _mesh_edit(cfg, model, scene, used, face_views, onehot, cls, table, folder.parent)
        meshes = (mesh_rec.pop("_mesh"), mesh_rec.pop("_after_mesh"))
    rows = []
    for t in targets:
        src = sources[t]
        r = _reblend(cfg, model, scene, t, src, edited, onehot, background, meshes)
        lifted = r["labels"].argmax(-1) == cls  # [H, W]
        rows.append(_target_row(t, src, r, lifted))
        _write_target(folder / f"{t:03d}", scene.images[t].numpy(), r, lifted, edited[src[0]].numpy())
    return {"scene": es.name, "action": cfg.action, "label": target_label, "path": cfg.path, "reencode": cfg.reencode,
            "labels": cfg.labels, "edited_views": used, "panel_tiles": "true image | lifted object mask | before | "
            "after | first edited source", "targets": rows, "mesh": mesh_rec if cfg.geometry else None}


def _views(cfg: EditConfig, es) -> tuple[list[int], list[int], dict[int, list[int]], list[int]]:
    """``(targets, pool, sources per target, face views)``; the face views (the sources, then the pool views nearest
    the first target) only when a mesh is needed."""
    scene = es.scene
    targets, pool = given_targets(es.protocol, scene, cfg.targets, cfg.num_views, es.path)
    sources = {t: select_sources(scene, scene.cameras[t], pool, cfg.num_views) for t in targets}
    used = sorted({v for s in sources.values() for v in s})
    face_views = []
    if cfg.path == "mesh" or cfg.geometry:
        near = select_sources(scene, scene.cameras[targets[0]], pool, len(pool))
        face_views = (used + [v for v in near if v not in used])[:max(cfg.face_views, len(used))]
    return targets, pool, sources, face_views


def _target_label(cfg: EditConfig, es, labels, first_sources: list[int], table: np.ndarray) -> int:
    """The object's label value: --label, or the label under --click in --click-view."""
    if cfg.click is not None:
        view = first_sources[0] if cfg.click_view is None else cfg.click_view
        target_label = E.label_at(labels, view, *cfg.click)
    else:
        target_label = int(cfg.label)
    if target_label not in set(table.tolist()):
        raise InputError(f"label {target_label} is not in the scene (labels: {table.tolist()})", es.path,
                         "pick one of those values")
    return target_label


def _edit_sources(cfg: EditConfig, scene, used: list[int], objects, background, folder: Path):
    """All images with the object (``objects``: its pixels in the ``used`` views) edited in the ``used`` views (written under ``sources/``). ``# [N, H, W, 3]``"""
    edited_used = E.edit_images(scene.images[used], objects, cfg.action, cfg.colour, cfg.fill, background,
                                cfg.dilation)
    edited = scene.images.clone()
    edited[used] = edited_used.float()
    for v in used:
        write_image(folder / "sources" / f"{v:03d}_edited.png", edited[v].numpy())
    return edited


def _onehot(labels, table: np.ndarray):
    """One-hot classes of the label maps (all zero where a label is not in ``table``). ``# [N, H, W, C]``"""
    import torch

    classes = P.labels_to_classes(labels, table)
    onehot = torch.from_numpy(np.eye(len(table), dtype=np.float32)[np.clip(classes, 0, None)])
    onehot[torch.from_numpy(classes < 0)] = 0
    return onehot


def _reblend(cfg: EditConfig, model, scene, t: int, src: list[int], edited, onehot, background, meshes) -> dict:
    """Target ``t`` before and after the edit (and its lifted labels), through the model's ray weights or the mesh
    (``meshes``: the mesh before and after the edit)."""
    import functools

    import torch

    s_orig = Sources.from_scene(scene, src)
    s_edit = replace(s_orig, images=edited[src].to(s_orig.images.dtype))
    if cfg.path == "volumetric":
        with torch.no_grad():
            feats = model.encode(s_orig)
            after_feats = model.encode(s_edit) if cfg.reencode else None
            return E.reblend_volumetric(model, feats, scene.cameras[t], scene.images[src], edited[src], onehot[src],
                                        after_feats, cfg.chunk)
    opts = MeshRenderOptions(background=background, visibility=cfg.visibility, cull_back_faces=False)
    changed_mesh = cfg.action == "remove"  # the after view lacks the object's faces
    after = None
    if cfg.reencode or changed_mesh:
        after = functools.partial(MeshRenderer, model, meshes[1] if changed_mesh else meshes[0],
                                  s_edit if cfg.reencode else s_orig, opts)
    with MeshRenderer(model, meshes[0], s_orig, opts) as before:
        return E.reblend_mesh(before, scene.cameras[t], scene.images[src], edited[src], onehot[src], after)


def _target_row(t: int, src: list[int], r: dict, lifted) -> dict:
    """How much changed inside and outside the object's lifted pixels."""
    delta = (r["after"] - r["before"]).abs().amax(-1)  # [H, W]
    diff = delta > 1e-4

    def frac(x, m):
        return float(x[m].float().mean()) if m.any() else 0.0

    return {"target": t, "sources": src, "object_pixels": int(lifted.sum()),
            "changed_inside": frac(diff, lifted), "changed_outside": frac(diff, ~lifted),
            "mean_change_inside": frac(delta, lifted), "mean_change_outside": frac(delta, ~lifted)}


def _write_target(stem: Path, img: np.ndarray, r: dict, lifted, first_edited: np.ndarray) -> None:
    """``<view>_before.png``, ``_after.png``, ``_mask.png`` and ``_panel.png``."""
    mask_pic = np.where(lifted.numpy()[..., None], 0.5 * img + 0.5 * np.array([1.0, 0.0, 0.0]), img)
    write_image(Path(f"{stem}_before.png"), r["before"].clamp(0, 1).numpy())
    write_image(Path(f"{stem}_after.png"), r["after"].clamp(0, 1).numpy())
    write_image(Path(f"{stem}_mask.png"), mask_pic)
    tiles = [img, mask_pic, r["before"].clamp(0, 1).numpy(), r["after"].clamp(0, 1).numpy(), first_edited]
    write_image(Path(f"{stem}_panel.png"), X.panel(tiles))


def _mesh_edit(cfg: EditConfig, model, scene, used, views, onehot, cls: int, table, out: Path) -> dict:
    """Face labels and colours lifted from ``views``; delete/recolour ``cls``; export GLBs."""

    mesh, source = scene_mesh(model, scene, used, cfg.mesh)
    maps, seen, known = face_maps(model, mesh, Sources.from_scene(scene, views),
                                  {"labels": (onehot[views], "probabilities"), "rgb": (scene.images[views], "regression")})
    labels = labels_from_probs(mesh, maps["labels"], seen)
    colours = np.where(known[:, None], maps["rgb"], 0.5)
    edited_mesh, edited_colours, keep = E.edit_faces(mesh, colours, labels, cls, cfg.action, cfg.colour)
    rec = {"source": source, "face_views": views, "faces": len(mesh.faces), "faces_hit": int((labels == cls).sum()),
           "faces_seen": float(seen.mean()), "faces_kept": len(keep), "_mesh": mesh, "_after_mesh": edited_mesh}
    gt = gt_face_labels(scene) if source == "gt" else None
    if gt is not None:

        g = labels_to_classes(gt, table)
        area = np.asarray(mesh.area_faces)
        rec["face_label_accuracy"] = float((labels == g).mean())
        rec["face_label_accuracy_area"] = float((area * (labels == g)).sum() / area.sum())
    if cfg.geometry:
        T = scene.to_input.double().numpy()
        for name, m, c in (("mesh_original.glb", mesh, colours), ("mesh_edited.glb", edited_mesh, edited_colours)):
            write_mesh(E.coloured_mesh(m, c), [out / name], T)
        rec["files"] = ["mesh_original.glb", "mesh_edited.glb"]
    return rec
