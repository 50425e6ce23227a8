"""Image retrieval from the SIFT features already in a COLMAP database: loop pairs for sequential matching,
the pairs a photo folder is matched on.

A video that walks around a subject comes back to where it started; sequential matching (each frame
with its next few) never pairs its last frames with its first. :func:`similar_pairs` finds such pairs
offline, without COLMAP's downloaded vocabulary tree: a small visual vocabulary is clustered from a
sample of the capture's own descriptors (:func:`scipy.cluster.vq.kmeans2`), each image becomes a
tf-idf weighted histogram of its words, and each image is paired with the images most similar to it
that are further than ``skip`` frames away. :func:`chosen_pairs` picks a photo folder's pairs the same way
(neighbours in name order plus the most similar images) and :func:`bridge_pairs` the pairs that may join
groups of images the verified matches left apart; :func:`image_pairs` gives the exhaustive and sequential pairs and
:func:`matcher_kind` which of the three a capture gets.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

EXHAUSTIVE_MAX = 20  # "auto" matching of photos: exhaustive up to this many images (190 pairs), retrieval above
WORDS = 256
"""Visual words of the vocabulary (a few hundred suffice for the frames of one capture)."""
SAMPLE = 20000
"""Descriptors sampled to cluster the vocabulary."""


def read_descriptors(db_path: Path, names: list[str]) -> list[np.ndarray]:
    """SIFT descriptors of each of ``names`` [K_i, 128] float32, unit length (empty when it has none)."""
    import pycolmap  # lazy: the optional 'capture' extra

    with pycolmap.Database.open(str(db_path)) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        out = []
        for n in names:
            d = np.zeros((0, 128), np.float32)
            if n in ids:
                raw = db.read_descriptors(ids[n])  # pycolmap 4: FeatureDescriptors, its .data [K, 128] uint8
                d = np.asarray(getattr(raw, "data", raw), np.float32)
            out.append(d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-6))
    return out


def word_histograms(descriptors: list[np.ndarray], words: int = WORDS, seed: int = 0) -> np.ndarray:
    """[N, words] tf-idf weighted, unit-length histograms of each image's visual words."""
    from scipy.cluster.vq import kmeans2, vq

    rng = np.random.default_rng(seed)
    every = np.concatenate([d for d in descriptors if len(d)] or [np.zeros((1, 128), np.float32)])  # [D, 128]
    sample = every[rng.choice(len(every), min(SAMPLE, len(every)), replace=False)]
    words = max(1, min(words, len(sample) // 4))
    with warnings.catch_warnings():  # a word no descriptor falls in (few, alike frames) is harmless: never counted
        warnings.filterwarnings("ignore", "One of the clusters is empty", UserWarning)
        centres, _ = kmeans2(sample, words, iter=10, minit="points", seed=seed)  # [words, 128]; "++": O(words^2 n)
    hist = np.zeros((len(descriptors), words), np.float64)
    for i, d in enumerate(descriptors):
        if len(d):
            hist[i] = np.bincount(vq(d, centres)[0], minlength=words)
    idf = np.log(len(descriptors) / np.maximum((hist > 0).sum(0), 1))  # [words]
    hist = hist / np.maximum(hist.sum(1, keepdims=True), 1) * idf
    return hist / np.maximum(np.linalg.norm(hist, axis=1, keepdims=True), 1e-12)


def similar_pairs(db_path: Path, names: list[str], per_image: int, skip: int, seed: int = 0) -> list[tuple[int, int]]:
    """Index pairs ``(i, j)``, ``i < j``: each image of ``names`` (in capture order) with its ``per_image``
    most similar images (:func:`word_histograms`, cosine similarity) among those more than ``skip``
    positions away."""
    if per_image < 1 or len(names) < skip + 2:
        return []
    return nearest_pairs(similarity(db_path, names, seed), per_image, skip)


def nearest_pairs(sim: np.ndarray, per_image: int, skip: int) -> list[tuple[int, int]]:
    """Index pairs ``(i, j)``, ``i < j``: each row of the similarity matrix ``sim`` [N, N] with its
    ``per_image`` highest columns more than ``skip`` positions away."""
    sim = np.array(sim, dtype=np.float64)
    idx = np.arange(len(sim))
    sim[np.abs(idx[:, None] - idx[None, :]) <= skip] = -np.inf
    pairs = set()
    for i in range(len(sim)):
        for j in np.argsort(-sim[i], kind="stable")[:per_image]:
            if np.isfinite(sim[i, j]):
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def similarity(db_path: Path, names: list[str], seed: int = 0) -> np.ndarray:
    """[N, N] cosine similarity of the images' visual-word histograms (:func:`word_histograms`)."""
    hist = word_histograms(read_descriptors(db_path, names), seed=seed)
    return hist @ hist.T


def chosen_pairs(sim: np.ndarray, near: int, per_image: int) -> list[tuple[int, int]]:
    """Index pairs ``(i, j)``, ``i < j``, to match: each image with the ``near`` next ones in name order
    (photos of one walk are numbered in order) and with its ``per_image`` most similar among the rest
    (``sim`` [N, N], :func:`similarity`)."""
    n = len(sim)
    seq = {(i, i + d) for i in range(n) for d in range(1, near + 1) if i + d < n}
    return sorted(seq | set(nearest_pairs(sim, per_image, near)))


def bridge_pairs(sim: np.ndarray, groups: list[list[int]], per_group: int, done: set) -> list[tuple[int, int]]:
    """Index pairs ``(i, j)``, ``i < j``, not in ``done``: for each group of images (indices; groups that
    share no verified match, largest first) but the first, its ``per_group`` most similar pairs with
    images outside it, so that another round of matching may join the groups (``sim`` [N, N])."""
    out = set()
    for g in groups[1:]:
        inside = np.zeros(len(sim), bool)
        inside[g] = True
        cand = [(sim[i, j], min(i, j), max(i, j)) for i in g for j in np.flatnonzero(~inside)
                if (min(i, j), max(i, j)) not in done]
        out |= {(int(i), int(j)) for _, i, j in sorted(cand, key=lambda c: -c[0])[:per_group]}
    return sorted(out)


def image_pairs(n: int, sequential: bool, overlap: int) -> list[tuple[int, int]]:
    """Index pairs ``(i, j)``, ``i < j``: all of them, or neighbours within ``overlap`` plus 2^k apart."""
    if not sequential:
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    pairs = set()
    for i in range(n):
        for d in range(1, overlap + 1):
            if i + d < n:
                pairs.add((i, i + d))
        d = 2 * overlap
        while i + d < n:  # quadratic overlap: reach further back along long sequences
            pairs.add((i, i + d))
            d *= 2
    return sorted(pairs)


def matcher_kind(matcher: str, n: int, video: bool) -> str:
    """The pairs :attr:`SfmOptions.matcher` means for ``n`` images: exhaustive, sequential or retrieval."""
    if matcher != "auto":
        return matcher
    return "sequential" if video else "exhaustive" if n <= EXHAUSTIVE_MAX else "retrieval"
