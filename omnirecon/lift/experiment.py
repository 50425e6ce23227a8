"""Shared by ``omnirecon lift`` and ``bench/lift.py``: lift several predictors into one target view with
one render, score predict-then-blend against render-then-predict, and draw the maps.

What each predictor is scored against (``score_target``):

* label predictors (``oracle-labels``, ``noisy-labels``, ``knn-labels``): mIoU (in %, classes present
  in the GT or the prediction) and pixel accuracy against the target's ground-truth labels. Oracles
  cannot run on a render, so they have no render-then-predict row; ``noisy-labels`` is compared with
  its own output on the target view (``input``: the noisy labels the lift has to repair);
  ``knn-labels`` has a render-then-predict row and an ``input`` row (the classifier on the true target
  image, the 2-D model's own ceiling).
* edges (``sobel``, ``canny``, ``hed``): the pseudo-GT is the same predictor on the true target image (the
  paper's likely protocol). ``l1`` (lower is better) and ``fscore`` (binary at ``EDGE_THRESHOLD``, 1 px
  tolerance); ``fscore_labels``: F-score against the object boundaries of the GT labels when the
  scene has labels (edges of *geometry*, which texture edges cannot match).
* ``harris``: pseudo-GT is Harris on the true target image; ``l1`` of the heat maps (the paper's
  keypoint error) and ``fscore`` of their peaks within 2 px.
* ``oracle-normals``: mean angular error (degrees) against the target's GT normals.
* ``slic``, ``oracle-depth``: not scored (per-view superpixel ids / per-view depths; see predictors).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from omnirecon.lift import metrics as M
from omnirecon.lift.predictors import Predictor, labels_to_classes

EDGE_THRESHOLD = {"sobel": 0.2, "canny": 0.5, "hed": 0.5}
"""Binarisation threshold of edge maps for the F-score (Sobel: magnitude/0.5 >= 0.2; Canny lifts are soft;
HED: edge probability >= 0.5)."""
LABEL_PREDICTORS = ("oracle-labels", "noisy-labels", "knn-labels")


def score_target(pred: Predictor, lifted: Tensor, rendered: Tensor | None, scene, t: int) -> dict:
    """Metrics of one predictor on target view ``t`` of ``scene``: ``{"lift": {...}, "render": {...} | None,
    "input": {...} | None}`` (``render``: render-then-predict; ``input``: the predictor on the true image)."""
    name = pred.name
    gt_img = scene.images[t]
    if name in LABEL_PREDICTORS:
        if scene.labels is None:
            return {}
        table = np.asarray(pred.meta["class_ids"])
        gt = labels_to_classes(scene.labels[t], table)
        C = len(table)

        def seg(m):
            r = M.iou_from_confusion(M.confusion(m.argmax(-1), gt, C))
            return {"miou": 100 * r["miou"], "accuracy": 100 * r["accuracy"]}

        out = {"lift": seg(lifted), "render": None if rendered is None else seg(rendered)}
        out["input"] = None if name == "oracle-labels" else seg(pred(gt_img, t))
        return out
    if name in EDGE_THRESHOLD:
        thr = EDGE_THRESHOLD[name]
        ref = pred(gt_img)[..., 0]
        bnd = None if scene.labels is None else M.label_boundaries(scene.labels[t])

        def edge(m):
            m = m[..., 0]
            r = {"l1": M.map_l1(m, ref), "fscore": M.edge_fscore(m, ref >= thr, 1.0, thr)["fscore"]}
            if bnd is not None:
                r["fscore_labels"] = M.edge_fscore(m, bnd, 1.0, thr)["fscore"]
            return r

        out = {"lift": edge(lifted), "render": None if rendered is None else edge(rendered), "input": None}
        if bnd is not None:
            out["input"] = {"fscore_labels": M.edge_fscore(ref, bnd, 1.0, thr)["fscore"]}
        return out
    if name == "harris":
        ref = pred(gt_img)[..., 0]

        def kp(m):
            r = M.keypoint_error(m[..., 0], ref)
            return {"l1": r["l1"], "fscore": r["fscore"]}

        return {"lift": kp(lifted), "render": None if rendered is None else kp(rendered), "input": None}
    if name == "oracle-normals" and scene.normals is not None:
        return {"lift": {"angle_deg": M.normal_error(lifted, scene.normals[t])}, "render": None, "input": None}
    return {}


# ---------------------------------------------------------------------- pictures
def palette(n: int) -> np.ndarray:
    """``n`` distinct colours ``# [n, 3]`` in [0, 1] (tab20, then repeated)."""
    import matplotlib

    cmap = matplotlib.colormaps["tab20"]
    return np.array([cmap(i % 20)[:3] for i in range(max(n, 1))], np.float32)


def colourise(m: Tensor, kind: str, name: str = "", scale: float | None = None) -> np.ndarray:
    """A map ``# [H, W, C]`` as an RGB picture ``# [H, W, 3]``: class colours (argmax) for probabilities,
    ``(n + 1) / 2`` for 3-channel regression (normals), a magma heat map for 1 channel (divided by
    ``scale``, default its maximum for depth-like maps, 1 otherwise), a 3-d PCA for embeddings."""
    import matplotlib

    a = m.detach().float().cpu().numpy()
    if kind == "probabilities":
        return palette(a.shape[-1])[a.argmax(-1)]
    if kind == "regression" and a.shape[-1] == 3:
        return np.clip((a + 1) / 2, 0, 1)
    if kind == "regression" and a.shape[-1] == 1:
        s = scale if scale is not None else (max(float(a.max()), 1e-12) if name == "oracle-depth" else 1.0)
        return matplotlib.colormaps["magma"](np.clip(a[..., 0] / s, 0, 1))[..., :3].astype(np.float32)
    flat = a.reshape(-1, a.shape[-1])
    flat = flat - flat.mean(0)
    _, _, v = np.linalg.svd(flat, full_matrices=False)
    p = flat @ v[:3].T
    p = (p - p.min(0)) / np.maximum(p.max(0) - p.min(0), 1e-12)
    return p.reshape(*a.shape[:2], -1)[..., :3]


def overlay(image: Tensor, picture: np.ndarray, alpha: float = 0.55) -> np.ndarray:
    """``picture`` blended over ``image # [H, W, 3]``."""
    return (1 - alpha) * image.float().cpu().numpy() + alpha * picture


def panel(tiles: list[np.ndarray], scale: int = 2, gap: int = 2) -> np.ndarray:
    """Tiles side by side, each upscaled ``scale`` times (nearest), white gaps."""
    big = [np.kron(t, np.ones((scale, scale, 1), np.float32)) for t in tiles]
    h = big[0].shape[0]
    white = np.ones((h, gap, 3), np.float32)
    out = []
    for i, t in enumerate(big):
        out += [t] if i == 0 else [white, t]
    return np.concatenate(out, 1)


def mean_rows(rows: list[dict]) -> dict:
    """Average the per-target metric dicts of :func:`score_target` (``{"lift": {...}, ...}``) key by key."""
    out: dict = {}
    for part in ("lift", "render", "input"):
        vals: dict[str, list[float]] = {}
        for r in rows:
            for k, v in (r.get(part) or {}).items():
                if v is not None and np.isfinite(v):
                    vals.setdefault(k, []).append(float(v))
        out[part] = {k: float(np.mean(v)) for k, v in vals.items()} or None
    out["targets"] = len(rows)
    return out


def torch_image(a) -> Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))


def knn_train_views(pool: list[int], used: set[int], count: int = 6) -> list[int]:
    """Up to ``count`` evenly spaced pool views that are no target's source: the labelled views the
    ``knn-labels`` classifier is fitted on (it never sees a source or target pixel)."""
    free = [v for v in pool if v not in used]
    if len(free) <= count:
        return free
    return [free[i] for i in np.unique(np.linspace(0, len(free) - 1, count).round().astype(int))]
