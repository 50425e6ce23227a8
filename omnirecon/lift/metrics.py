"""Scores for lifted 2-D predictions: mIoU, edge F-score, keypoint heat-map error, normal error."""

from __future__ import annotations

import numpy as np
import torch


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if torch.is_tensor(x) else np.asarray(x)


def confusion(pred, gt, num_classes: int, ignore_index: int | None = -1) -> np.ndarray:
    """Confusion matrix ``[gt, pred]`` of class maps ``pred, gt # [H, W]`` (pixels whose GT is
    ``ignore_index`` or outside ``0..num_classes-1`` are skipped). ``# [C, C]`` int64"""
    p, g = _np(pred).reshape(-1).astype(np.int64), _np(gt).reshape(-1).astype(np.int64)
    ok = (g >= 0) & (g < num_classes) & (p >= 0) & (p < num_classes)
    if ignore_index is not None:
        ok &= g != ignore_index
    return np.bincount(g[ok] * num_classes + p[ok], minlength=num_classes ** 2).reshape(num_classes, num_classes)


def iou_from_confusion(cm: np.ndarray) -> dict:
    """``{"miou", "iou": {class: IoU}, "accuracy"}``: IoU of every class present in the GT or the prediction
    (union > 0); mIoU is their mean (in [0, 1])."""
    tp = np.diag(cm).astype(np.float64)
    union = cm.sum(0) + cm.sum(1) - tp
    present = union > 0
    iou = np.where(present, tp / np.maximum(union, 1), np.nan)
    return {"miou": float(np.nanmean(iou)) if present.any() else float("nan"),
            "iou": {int(c): float(iou[c]) for c in np.flatnonzero(present)},
            "accuracy": float(tp.sum() / max(cm.sum(), 1))}


def miou(pred, gt, num_classes: int | None = None, ignore_index: int | None = -1) -> float:
    """Mean IoU (in [0, 1]) of class maps ``pred, gt # [H, W]`` over classes present in either."""
    if num_classes is None:
        num_classes = int(max(_np(pred).max(), _np(gt).max())) + 1
    return iou_from_confusion(confusion(pred, gt, num_classes, ignore_index))["miou"]


def label_boundaries(labels) -> np.ndarray:
    """Pixels whose 4-neighbourhood holds another label (both sides of each boundary). ``# [H, W]`` bool"""
    lab = _np(labels)
    b = np.zeros(lab.shape, bool)
    dy, dx = lab[1:] != lab[:-1], lab[:, 1:] != lab[:, :-1]
    b[1:] |= dy
    b[:-1] |= dy
    b[:, 1:] |= dx
    b[:, :-1] |= dx
    return b


def edge_fscore(pred, gt, tolerance: float = 1.0, threshold: float = 0.5) -> dict:
    """Edge precision / recall / F-score with a pixel ``tolerance``: a predicted edge pixel (``pred >=
    threshold``) is correct if a GT edge pixel lies within ``tolerance`` px (Euclidean) and vice versa.
    ``pred, gt # [H, W]`` (``gt`` boolean or thresholded the same way). Empty maps score 1 if both are empty."""
    from scipy.ndimage import distance_transform_edt

    p = _np(pred) >= threshold
    g = _np(gt).astype(np.float64) >= threshold if _np(gt).dtype != bool else _np(gt)
    if not p.any() and not g.any():
        return {"precision": 1.0, "recall": 1.0, "fscore": 1.0}
    if not p.any() or not g.any():
        return {"precision": float(not p.any()), "recall": float(not g.any()), "fscore": 0.0}
    dist_to_g = distance_transform_edt(~g)
    dist_to_p = distance_transform_edt(~p)
    precision = float((dist_to_g[p] <= tolerance).mean())
    recall = float((dist_to_p[g] <= tolerance).mean())
    f = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return {"precision": precision, "recall": recall, "fscore": f}


def map_l1(pred, gt, mask=None) -> float:
    """Mean absolute error of two maps (e.g. edge or keypoint heat maps), optionally over ``mask``."""
    d = np.abs(_np(pred).astype(np.float64) - _np(gt).astype(np.float64))
    if mask is not None:
        m = _np(mask).astype(bool)
        d = d[m] if d.shape[:m.ndim] == m.shape else d
    return float(d.mean()) if d.size else float("nan")


def keypoints(heat, min_distance: int = 2, threshold_rel: float = 0.1) -> np.ndarray:
    """Peaks of a heat map ``# [H, W]`` (``skimage.feature.peak_local_max``). ``# [P, 2]`` (row, col)"""
    from skimage.feature import peak_local_max

    h = _np(heat).astype(np.float64)
    if h.max() <= 0:
        return np.zeros((0, 2), np.int64)
    return peak_local_max(h, min_distance=min_distance, threshold_rel=threshold_rel, exclude_border=False)


def keypoint_error(pred, gt, tolerance: float = 2.0, min_distance: int = 2, threshold_rel: float = 0.1) -> dict:
    """Keypoint heat-map error: ``l1`` between the heat maps ``pred, gt # [H, W]`` (the paper's keypoint
    error, lower is better) and ``precision / recall / fscore`` of their peaks matched within
    ``tolerance`` px."""
    shape = _np(gt).shape
    pk, gk = np.zeros(shape, bool), np.zeros(shape, bool)
    for dst, src in ((pk, pred), (gk, gt)):
        pts = keypoints(src, min_distance, threshold_rel)
        dst[pts[:, 0], pts[:, 1]] = True
    f = edge_fscore(pk, gk, tolerance)
    return {"l1": map_l1(pred, gt), **f, "peaks_pred": int(pk.sum()), "peaks_gt": int(gk.sum())}


def normal_error(pred, gt) -> float:
    """Mean angle in degrees between normal maps ``# [H, W, 3]`` over pixels where the GT is non-zero."""
    p, g = _np(pred).astype(np.float64), _np(gt).astype(np.float64)
    ok = np.linalg.norm(g, axis=-1) > 0.5
    if not ok.any():
        return float("nan")
    p = p[ok] / np.maximum(np.linalg.norm(p[ok], axis=-1, keepdims=True), 1e-12)
    g = g[ok] / np.linalg.norm(g[ok], axis=-1, keepdims=True)
    return float(np.degrees(np.arccos(np.clip((p * g).sum(-1), -1, 1))).mean())
