"""Meshes for the mesh path of lifting, and per-face labels lifted onto them.

* :func:`scene_mesh`: the mesh of a scene in its (normalised) scene frame: a procedural scene's exact
  mesh (``omnirecon.mesh.geometry.ground_truth_mesh``), the model's baked mesh (``omnirecon mesh``'s
  protocol, :func:`omnirecon.mesh.build.mesh_from_model`) or a mesh file in the input frame.
* :func:`lift_faces`: any per-view map blended at every face centroid, seen from a point in front of
  the face (``distance`` along its normal, both sides tried), with the sources in which the centroid
  is occluded masked out (the renderer's depth test); faces no source sees get weight 0.
* :func:`face_maps`: any maps per face (colours, ...); faces no source sees take the mean of their seen
  neighbours (:func:`propagate`, over shared edges);
* :func:`face_labels` / :func:`labels_from_probs`: the argmax of the lifted labels on seen faces, spread to
  the other faces of their component by neighbour majority, else unknown (-1).
* :func:`gt_face_labels`: the procedural mesh's own ``object_id`` per face, for scoring.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh
from torch import Tensor

from omnirecon.errors import InputError
from omnirecon.lift.blend import lift_points, normalise
from omnirecon.mesh.build import MeshOptions, mesh_from_model
from omnirecon.mesh.files import read_mesh
from omnirecon.mesh.geometry import ground_truth_mesh, load_mesh_file
from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions


def scene_mesh(model, scene, views: list[int], mesh: str | Path = "auto") -> tuple[trimesh.Trimesh, str]:
    """The mesh to lift through, in the scene frame, and where it came from (``"gt"``, ``"model"`` or the
    file). ``mesh``: ``"gt"`` (the procedural scene's exact mesh), ``"model"`` (baked from ``model``'s depth
    at ``views``), ``"auto"`` (gt when the scene has one, else model) or a mesh file in the input frame."""

    spec = str(mesh)
    if spec in ("auto", "gt"):
        gt = ground_truth_mesh(scene)
        if gt is not None:
            return gt, "gt"
        if spec == "gt":
            raise InputError("the scene has no exact mesh", scene.path, "use --mesh model or a mesh file")
    if spec in ("auto", "model"):

        made = mesh_from_model(model, scene, views, MeshOptions(depth="model"), device=next(model.parameters()).device)
        if len(made.mesh.faces) == 0:
            raise InputError("the model's mesh is empty", scene.path, "use more --num-views or a mesh file")
        return made.mesh, "model"
    path = Path(spec)
    if not path.is_file():
        raise InputError("mesh file not found", path, "pass gt, model, auto or a .ply/.obj/.glb file")
    return read_mesh(path, scene.to_input), str(path)


def gt_face_labels(scene) -> np.ndarray | None:
    """The ``object_id`` of every face of the procedural mesh, in :func:`scene_mesh`'s ``"gt"`` face order
    (label values as in ``scene.labels``: 1..254 objects, 255 ground), or None. ``# [F]`` int64"""
    if scene.mesh_path is None:
        return None
    raw = load_mesh_file(scene.mesh_path, "ground-truth mesh",
                         "fix the scene's mesh file, or remove its mesh_path entry").metadata.get("_ply_raw", {})
    data = raw.get("face", {}).get("data")
    if data is None or "object_id" not in (data.dtype.names or ()):
        return None
    return np.asarray(data["object_id"]).astype(np.int64)


def face_frames(mesh: trimesh.Trimesh, distance: float) -> tuple[Tensor, Tensor, Tensor]:
    """Face centroids ``# [F, 3]``, and viewpoints ``distance`` in front of (``+normal``) and behind them."""
    c = torch.from_numpy(np.array(mesh.triangles_center, dtype=np.float64))
    n = torch.from_numpy(np.array(mesh.face_normals, dtype=np.float64))
    return c, c + distance * n, c - distance * n


def lift_faces(renderer, mesh: trimesh.Trimesh, signals: Tensor, kind: str, distance: float, strict: bool = False
               ) -> tuple[Tensor, Tensor]:
    """Lift ``signals # [K, H', W', C]`` to every face centroid of ``mesh`` (:func:`omnirecon.lift.blend.lift_points`;
    ``strict``: with its nearest-pixel depth test against the sources' rasterized depth; on procedural
    scenes at 64 px it drops faces at their own silhouettes as well and did not help). The viewpoint is
    ``distance`` in front of the face; where no source sees the centroid from there, the side behind
    (meshes whose winding is not outward). Returns ``# [F, C]`` and ``seen # [F]``."""

    depths = renderer.source_depths() if strict else None  # [K, H, W]
    c, front, back = face_frames(mesh, distance)
    values, seen = lift_points(renderer, c, front, signals, kind, depths=depths)
    if (~seen).any():
        idx = (~seen).nonzero()[:, 0]
        v2, s2 = lift_points(renderer, c[idx], back[idx], signals, kind, depths=depths)
        values[idx[s2]] = v2[s2]
    return values, seen


def propagate(mesh: trimesh.Trimesh, values: np.ndarray, known: np.ndarray, max_rounds: int = 1000
              ) -> tuple[np.ndarray, np.ndarray]:
    """Fill the faces that are not ``known`` with the mean of their known edge neighbours' ``values #
    [F, C]``, round by round (a filled face is known in the next round) until nothing changes. Returns the
    values and the new ``known # [F]`` (False only for components with no known face)."""
    out = np.array(values, dtype=np.float64)
    known = np.asarray(known, dtype=bool).copy()
    pairs = np.asarray(mesh.face_adjacency, dtype=np.int64).reshape(-1, 2)
    a, b = np.concatenate([pairs[:, 0], pairs[:, 1]]), np.concatenate([pairs[:, 1], pairs[:, 0]])  # a <- b
    for _ in range(max_rounds):
        todo = ~known[a] & known[b]
        if not todo.any():
            break
        total = np.zeros_like(out)
        count = np.zeros(len(out))
        np.add.at(total, a[todo], out[b[todo]])
        np.add.at(count, a[todo], 1.0)
        fill = count > 0
        out[fill] = total[fill] / count[fill, None]
        known |= fill
    return out, known


def face_maps(model, mesh: trimesh.Trimesh, sources, signals: dict[str, tuple[Tensor, str]],
              distance: float | None = None, fill: bool = True
              ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """Lift per-view maps ``{name: (maps # [K, H, W, C], kind)}`` of ``sources`` to every face centroid of
    ``mesh`` with the occlusion test on (:func:`lift_faces`; one blend for all maps). ``distance`` (the
    viewpoint's distance from each face) defaults to the mean distance of the source cameras to the mesh
    centre. With ``fill``, faces no source sees take the mean of their neighbours (:func:`propagate`).
    Returns ``{name: # [F, C]}`` (normalised by kind; faces still unknown: uniform / zero), ``seen # [F]``
    (lifted directly) and ``known # [F]`` (seen or filled)."""

    if distance is None:
        centre = torch.from_numpy(np.asarray(mesh.bounds, dtype=np.float64).mean(0))
        distance = float((sources.cameras.centers.double().cpu() - centre).norm(dim=-1).mean())
    names = list(signals)
    stacked = torch.cat([signals[n][0].float() for n in names], -1)  # [K, H, W, sum C]
    opts = MeshRenderOptions(visibility=True, cull_back_faces=False)
    with MeshRenderer(model, mesh, sources, opts) as renderer:
        values, seen = lift_faces(renderer, mesh, stacked, "regression", distance)  # [F, sum C], [F]
    values = values.double().numpy()
    known = seen.numpy()
    if fill:
        values, known = propagate(mesh, values, known)
    out, c = {}, 0
    for n in names:
        width = signals[n][0].shape[-1]
        part = torch.from_numpy(values[:, c:c + width])
        out[n] = normalise(part, torch.from_numpy(known.astype(np.float64)), signals[n][1]).numpy()
        c += width
    return out, seen.numpy(), known


def labels_from_probs(mesh: trimesh.Trimesh, probs: np.ndarray, seen: np.ndarray, min_confidence: float = 0.0
                      ) -> np.ndarray:
    """Face labels from lifted class probabilities ``probs # [F, C]``: the argmax on faces that are ``seen``
    (with a top probability of at least ``min_confidence``), spread to the other faces of their component
    by neighbour majority (:func:`propagate`, round by round); -1 where nothing reaches. A threshold
    (e.g. 0.9) distrusts faces just behind a silhouette, which blend the occluder's label in, but region
    growing from few seeds then floods whole objects (one held-out scene: 637 faces deleted for 256). ``# [F]``"""
    probs = np.asarray(probs, np.float64)
    seeds = np.asarray(seen, bool) & (probs.max(-1) >= min_confidence)
    onehot = np.eye(probs.shape[1])[probs.argmax(-1)] * seeds[:, None]
    votes, known = propagate(mesh, onehot, seeds)
    return np.where(known, votes.argmax(-1), -1)


def face_labels(model, mesh: trimesh.Trimesh, sources, label_maps: Tensor, min_confidence: float = 0.0,
                distance: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-face class indices from one-hot (or probability) ``label_maps # [K, H, W, C]`` of ``sources``:
    lifted at the centroids with the occlusion test (:func:`face_maps`), then :func:`labels_from_probs`.
    Returns the labels ``# [F]`` (-1: unknown) and ``seen # [F]``."""
    maps, seen, _ = face_maps(model, mesh, sources, {"labels": (label_maps, "probabilities")}, distance, fill=False)
    return labels_from_probs(mesh, maps["labels"], seen, min_confidence), seen
