"""Geometry metrics: Chamfer distance and F-score of meshes, depth errors, silhouette IoU, pictures.

**Chamfer and F-score** follow the DTU evaluation script (``dtu_eval.py`` of VolRecon/Omni-Recon):

* both surfaces are sampled uniformly by area (``count`` points each, seeded);
* *accuracy* = mean distance from predicted points to the ground truth, *completeness* = mean
  distance from ground-truth points to the prediction, *Chamfer* = their mean;
* distances of ``max_dist`` or more are **left out** of each mean (DTU drops them: 20 mm, about
  2.5 % of DTU's ~800 mm bounds diagonal, hence ``MAX_DIST = 0.025`` of the diagonal); the
  fractions left out are reported;
* *precision* / *recall* are the fractions of predicted / ground-truth points within
  ``threshold`` of the other surface (all points count), *F-score* their harmonic mean.
  Default threshold: ``FSCORE_THRESHOLD = 0.01`` of the bounds diagonal.

Ground truth is restricted like DTU's observation mask: only ground-truth points that some view
of the scene actually sees (checked against the scene's ground-truth depth maps) count, and only
predicted points inside the bounds (grown by ``max_dist``) count.

Rasterisation (silhouettes, mesh depth, the hidden-face test of mesh cleaning, pictures) reuses
the procedural generator's exact z-buffer rasteriser (:func:`omnirecon.render.zbuffer.rasterize`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.data.io import write_image
from omnirecon.errors import InputError
from omnirecon.render.zbuffer import Fragments, rasterize

FSCORE_THRESHOLD = 0.01
"""F-score distance threshold as a fraction of the bounds diagonal."""
MAX_DIST = 0.025
"""Distances at or above this fraction of the bounds diagonal are left out of the Chamfer means (DTU: 20 mm)."""
GROUND_ID = 255
"""``object_id`` of the ground / backdrop faces in a procedural scene's ``mesh.ply``."""


# ---------------------------------------------------------------------- point sets
def sample_points(mesh: trimesh.Trimesh, count: int, seed: int = 0) -> np.ndarray:
    """``count`` points uniformly distributed over the area of ``mesh`` (seeded). ``# [count, 3]``"""
    if len(mesh.faces) == 0 or count < 1:
        return np.zeros((0, 3))
    tri = np.asarray(mesh.vertices, dtype=np.float64)[mesh.faces]  # [F, 3, 3]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if area.sum() <= 0:
        return np.zeros((0, 3))
    rng = np.random.default_rng(seed)
    face = rng.choice(len(tri), size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    flip = r1 + r2 > 1  # fold the unit square onto the triangle
    r1, r2 = np.where(flip, 1 - r1, r1), np.where(flip, 1 - r2, r2)
    t = tri[face]
    return t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])


def nearest_distances(query: np.ndarray, points: np.ndarray, workers: int = 1, upper: float = np.inf) -> np.ndarray:
    """Distance from each ``query # [Q, 3]`` point to its nearest neighbour in ``points`` (scipy cKDTree);
    ``inf`` for a point with none closer than ``upper`` (exact below it: the tree stops searching there,
    faster when many points are far, as a mesh's background is from an objects-only ground truth)."""
    from scipy.spatial import cKDTree

    if len(query) == 0:
        return np.zeros(0)
    if len(points) == 0:
        return np.full(len(query), np.inf)
    return cKDTree(points).query(query, k=1, workers=workers, distance_upper_bound=upper)[0]


def chamfer_fscore(pred: np.ndarray, gt: np.ndarray, threshold: float, max_dist: float = np.inf,
                   workers: int = 1) -> dict[str, float]:
    """Chamfer distance and F-score between point sets ``pred # [P, 3]`` and ``gt # [G, 3]``.

    Returns ``accuracy`` (pred -> gt), ``completeness`` (gt -> pred), ``chamfer`` (their mean),
    each a mean over distances below ``max_dist``; ``accuracy_dropped`` / ``completeness_dropped``
    (fraction of points at ``max_dist`` or more); ``precision``, ``recall``, ``fscore`` at
    ``threshold``. With no predicted point, the means are ``inf`` and the F-score 0.
    """
    # every number below only asks "closer than max_dist?" or "closer than threshold?": distances beyond both
    # may come back as inf (the same results, a faster search)
    bound = float(np.nextafter(max(max_dist, threshold), np.inf))
    d_acc = nearest_distances(pred, gt, workers, bound)
    d_comp = nearest_distances(gt, pred, workers, bound)

    def capped_mean(d):
        d = d[d < max_dist]
        return float(d.mean()) if len(d) else float("inf")

    acc, comp = capped_mean(d_acc), capped_mean(d_comp)
    precision = float((d_acc < threshold).mean()) if len(d_acc) else 0.0
    recall = float((d_comp < threshold).mean()) if len(d_comp) else 0.0
    f = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {"accuracy": acc, "completeness": comp, "chamfer": (acc + comp) / 2,
            "accuracy_dropped": float((d_acc >= max_dist).mean()) if len(d_acc) else 1.0,
            "completeness_dropped": float((d_comp >= max_dist).mean()) if len(d_comp) else 1.0,
            "precision": precision, "recall": recall, "fscore": f, "threshold": threshold, "max_dist": max_dist}


def mesh_chamfer(pred: trimesh.Trimesh, gt: trimesh.Trimesh, threshold: float, max_dist: float = np.inf,
                 count: int = 100_000, seed: int = 0, workers: int = 1) -> dict[str, float]:
    """:func:`chamfer_fscore` of ``count`` area-uniform samples on each mesh."""
    return chamfer_fscore(sample_points(pred, count, seed), sample_points(gt, count, seed + 1), threshold, max_dist,
                          workers)


# ---------------------------------------------------------------------- images
def depth_errors(pred: Tensor | np.ndarray, gt: Tensor | np.ndarray, mask=None) -> dict[str, float]:
    """Depth errors where both depths are positive (and ``mask``): ``abs_rel`` = mean |p - g| / g,
    ``rmse`` (scene units), ``delta1`` = fraction with max(p/g, g/p) < 1.25, ``coverage`` = fraction of
    ground-truth pixels that have a prediction. ``# [H, W]`` inputs (any leading dims)."""
    p, g = np.asarray(pred, dtype=np.float64), np.asarray(gt, dtype=np.float64)
    has_gt = g > 0 if mask is None else (g > 0) & np.asarray(mask, dtype=bool)
    both = has_gt & (p > 0) & np.isfinite(p)
    if not both.any():
        return {"abs_rel": float("nan"), "rmse": float("nan"), "delta1": float("nan"), "coverage": 0.0}
    p, g = p[both], g[both]
    return {"abs_rel": float((np.abs(p - g) / g).mean()), "rmse": float(np.sqrt(((p - g) ** 2).mean())),
            "delta1": float((np.maximum(p / g, g / p) < 1.25).mean()),
            "coverage": float(both.sum() / max(has_gt.sum(), 1))}


def mask_iou(pred, gt) -> float:
    """Intersection over union of two boolean masks (1.0 when both are empty)."""
    p, g = np.asarray(pred, dtype=bool), np.asarray(gt, dtype=bool)
    union = (p | g).sum()
    return float((p & g).sum() / union) if union else 1.0


def rasterize_mesh(vertices: np.ndarray, faces: np.ndarray, camera: Cameras, supersample: int = 1,
                   two_sided: bool = True, near: float = 1e-4) -> Fragments:
    """Visibility buffer of a mesh seen by one camera, at ``supersample`` samples per pixel side.

    Faces with a vertex closer than ``near`` to the camera plane are left out (no clipping), and
    with ``two_sided`` every face is also drawn with the opposite winding, so open surfaces are
    seen from both sides. Returns :class:`~omnirecon.render.zbuffer.Fragments` of size
    ``(H * s, W * s)`` whose face ids index ``faces``.
    """
    cam = camera.to(dtype=torch.float64)
    w2c = cam.w2c[0].numpy()
    K = cam.K[0].numpy().copy()
    K[:2] *= supersample
    W, H = cam.width * supersample, cam.height * supersample
    verts = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    z = verts @ w2c[2, :3] + w2c[2, 3]
    keep = np.flatnonzero((z[faces] > near).all(1))
    if len(keep) == 0:
        return Fragments(np.full((H, W), -1, dtype=np.int64), np.zeros((H, W, 3)), np.zeros((H, W)))
    used, local = np.unique(faces[keep], return_inverse=True)
    local = local.reshape(-1, 3)
    ids = keep
    if two_sided:
        local = np.concatenate([local, local[:, ::-1]])
        ids = np.concatenate([keep, keep])
    frags = rasterize(verts[used], local, K, w2c, W, H, near=near / 2)
    hit = frags.face >= 0
    frags.face[hit] = ids[frags.face[hit]]
    return frags


def mesh_depth(mesh: trimesh.Trimesh, camera: Cameras) -> np.ndarray:
    """z-depth of ``mesh`` at the pixel centres of ``camera``, 0 where it is not hit. ``# [H, W]``"""
    return rasterize_mesh(mesh.vertices, mesh.faces, camera).depth


def silhouette(mesh: trimesh.Trimesh, camera: Cameras) -> np.ndarray:
    """Pixels (centres) of ``camera`` covered by ``mesh``. ``# [H, W]`` bool"""
    return rasterize_mesh(mesh.vertices, mesh.faces, camera).face >= 0


def shaded_image(mesh: trimesh.Trimesh, camera: Cameras, supersample: int = 2,
                 colour=(0.75, 0.78, 0.85), background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """A picture of ``mesh`` from ``camera``: flat shading with a head light, ``supersample``^2 samples
    per pixel (box filter). ``# [H, W, 3]`` uint8"""
    frags = rasterize_mesh(mesh.vertices, mesh.faces, camera, supersample=supersample)
    cam = camera.to(dtype=torch.float64)
    H, W = frags.face.shape
    img = np.empty((H, W, 3))
    img[:] = background
    hit = frags.face >= 0
    if hit.any():
        normals = np.asarray(mesh.face_normals)[frags.face[hit]]  # [P, 3] world
        uv = np.stack(np.nonzero(hit)[::-1], -1).astype(np.float64) + 0.5  # (u, v) at the sample rate
        _, d = cam.rays(torch.from_numpy(uv / supersample)[None])
        lambert = np.abs(np.einsum("pc,pc->p", normals, d[0].numpy()))
        img[hit] = np.asarray(colour) * (0.25 + 0.75 * lambert)[:, None]
    img = img.reshape(H // supersample, supersample, W // supersample, supersample, 3).mean((1, 3))
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def save_picture(path: Path, mesh: trimesh.Trimesh, camera: Cameras, supersample: int = 2) -> Path:
    """Write :func:`shaded_image` as a PNG (atomically)."""

    write_image(Path(path), shaded_image(mesh, camera, supersample))
    return Path(path)


# ---------------------------------------------------------------------- scenes
def scene_scales(scene) -> dict[str, float]:
    """Bounds diagonal of ``scene`` and the default F-score threshold and Chamfer cap (scene units)."""
    diag = float((scene.bounds[1] - scene.bounds[0]).double().norm())
    return {"diagonal": diag, "threshold": FSCORE_THRESHOLD * diag, "max_dist": MAX_DIST * diag}


def load_mesh_file(path, what: str = "mesh file", fix: str = "pass a valid .ply, .obj or .glb triangle mesh"):
    """``trimesh.load(path, force="mesh")`` with one-line errors naming ``path`` (any parser failure, a file
    without triangles, non-finite vertices) and the parser's warnings kept off stderr. Small on purpose: the
    one place mesh files are read, until a mesh-file module owns it."""
    import warnings

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} {'is not a regular file' if path.exists() else 'does not exist'}", path, fix)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # e.g. NumPy's fromstring deprecation inside trimesh's PLY reader
            mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # noqa: BLE001 - trimesh raises many types for bad files
        raise InputError(f"cannot read {what} ({type(e).__name__}: {str(e)[:100]})", path, fix) from e
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"the {what} holds no triangles", path, fix)
    if not np.isfinite(np.asarray(mesh.vertices)).all():
        raise InputError(f"the {what} has non-finite vertices", path, fix)
    return mesh


def ground_truth_mesh(scene, objects_only: bool = False) -> trimesh.Trimesh | None:
    """The scene's exact mesh (``scene.mesh_path``) in the scene frame, or ``None`` without one.

    ``objects_only`` drops faces whose PLY ``object_id`` is the ground / backdrop (255).
    """
    if scene.mesh_path is None:
        return None
    gt = load_mesh_file(scene.mesh_path, "ground-truth mesh",
                        "fix the scene's mesh file, or remove its mesh_path entry")
    T = scene.mesh_to_scene.double().numpy()
    verts = np.asarray(gt.vertices, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
    faces = np.asarray(gt.faces)
    if objects_only:
        raw = gt.metadata.get("_ply_raw", {}).get("face", {}).get("data")
        if raw is not None and "object_id" in (raw.dtype.names or ()):
            faces = faces[np.asarray(raw["object_id"]) != GROUND_ID]
    out = trimesh.Trimesh(verts, faces, process=False)
    out.remove_unreferenced_vertices()
    return out


def observed(points: np.ndarray, scene, tolerance_px: float = 2.0, rel: float = 0.01) -> np.ndarray:
    """Points some view of ``scene`` sees, judged by its ground-truth depth maps. ``# [P]`` bool

    A point is seen by a view when it projects into the image onto a pixel whose depth ``d`` is
    within ``rel * d`` plus ``tolerance_px`` pixel footprints of the point's own depth (pixel
    centres differ from the point's exact projection). All points count when the scene has no
    depth maps.
    """
    if scene.depths is None:
        return np.ones(len(points), dtype=bool)
    cams = scene.cameras.to(dtype=torch.float64)
    seen = np.zeros(len(points), dtype=bool)
    pts = torch.from_numpy(points)
    for i in range(len(cams)):
        proj = cams[i].project(pts)
        inside = proj.in_image[0].numpy()
        col = proj.uv[0, :, 0].floor().long().clamp(0, cams.width - 1).numpy()
        row = proj.uv[0, :, 1].floor().long().clamp(0, cams.height - 1).numpy()
        d = scene.depths[i].double().numpy()[row, col]
        z = proj.depth[0].numpy()
        tol = rel * d + tolerance_px * z / float(cams.fx[i])
        seen |= inside & (d > 0) & (np.abs(d - z) <= tol)
    return seen


def evaluate_mesh(mesh: trimesh.Trimesh, scene, held_out, objects_only: bool = False, count: int = 100_000,
                  seed: int = 0) -> dict:
    """Every geometry metric ``scene`` allows for ``mesh`` (scene frame). Distances in scene units.

    * ``mask_iou``: silhouette of the mesh against the silhouette of what it should cover in the ``held_out``
      views (mean and per view; ``against`` names it): the object masks with ``objects_only`` or without
      exact depth; otherwise every surface the view sees (exact depth > 0: a procedural scene's masks hold
      its objects, not the ground a mesh made without masks keeps, which scored the demo's complete
      mesh 0.19);
    * ``depth``: :func:`depth_errors` of the mesh's depth against the ground-truth depth of ``held_out``;
    * ``chamfer``: :func:`chamfer_fscore` against the exact mesh of a procedural scene (its objects
      only with ``objects_only``), restricted to observed ground truth and to the bounds.
    """
    held_out = [int(i) for i in held_out]
    out: dict = {"held_out": held_out, "units": "scene", **{k: v for k, v in scene_scales(scene).items()}}
    cams = scene.cameras.to(dtype=torch.float64)
    frags = [rasterize_mesh(mesh.vertices, mesh.faces, cams[i]) for i in held_out] if held_out else []
    against = "masks" if scene.masks is not None and (objects_only or scene.depths is None) else \
        "exact depth" if scene.depths is not None else None
    if against and held_out:
        truth = [scene.masks[i].numpy() if against == "masks" else scene.depths[i].numpy() > 0 for i in held_out]
        ious = [mask_iou(f.face >= 0, t) for f, t in zip(frags, truth)]
        out["mask_iou"] = {"mean": float(np.mean(ious)), "per_view": ious, "against": against}
    if scene.depths is not None and held_out:
        pred = np.stack([f.depth for f in frags])
        gt = scene.depths[held_out].double().numpy()
        mask = None if not objects_only or scene.masks is None else scene.masks[held_out].numpy()
        out["depth"] = depth_errors(pred, gt, mask)
    gt_mesh = ground_truth_mesh(scene, objects_only)
    if gt_mesh is not None:
        scales = scene_scales(scene)
        gt_pts = sample_points(gt_mesh, count, seed + 1)
        gt_pts = gt_pts[observed(gt_pts, scene)]
        pred_pts = sample_points(mesh, count, seed)
        lo, hi = scene.bounds.double().numpy() + np.array([[-1.0], [1.0]]) * scales["max_dist"]
        pred_pts = pred_pts[((pred_pts >= lo) & (pred_pts <= hi)).all(1)]
        out["chamfer"] = chamfer_fscore(pred_pts, gt_pts, scales["threshold"], scales["max_dist"])
        out["chamfer"]["gt_points"] = len(gt_pts)
        out["chamfer"]["gt_extent"] = float(np.linalg.norm(np.ptp(gt_pts, axis=0))) if len(gt_pts) else float("nan")
        out["chamfer"]["objects_only"] = objects_only
    return out


def rendered_depth_errors(scene, cameras: Cameras, depths) -> dict:
    """:func:`depth_errors` of a model's depth maps ``# [N, H, W]`` at ``cameras`` against the exact
    mesh of a procedural scene rasterised there (ground included); ``{}`` without a mesh."""
    gt_mesh = ground_truth_mesh(scene)
    if gt_mesh is None:
        return {}
    gt = np.stack([mesh_depth(gt_mesh, cameras[i]) for i in range(len(cameras))])
    return {"rendered_depth": depth_errors(np.asarray(depths, dtype=np.float64), gt)}


def score_mesh(made, scene, held_out) -> dict:
    """Every metric of a :class:`~omnirecon.mesh.build.MeshResult` on ``scene`` (its frame), lengths in
    input units: :func:`evaluate_mesh` on the ``held_out`` views (objects only when the mesh was
    cleaned with masks), the fused depth maps against the exact mesh, and ``chamfer_rel`` = Chamfer
    distance over the extent of the scored ground truth (the diagonal of the bounding box of its
    observed surface points: the objects, not the whole bounds, when objects only)."""
    scored = evaluate_mesh(made.mesh, scene, held_out, objects_only=made.info["masks"])
    scored.update(rendered_depth_errors(scene, made.cameras, made.depths))
    if "chamfer" in scored:
        scored["chamfer_rel"] = scored["chamfer"]["chamfer"] / scored["chamfer"]["gt_extent"]
    return in_input_units(scored, scene.scale_to_input)


def in_input_units(metrics: dict, scale: float) -> dict:
    """A copy of :func:`evaluate_mesh`'s result with lengths multiplied by ``scale`` (``Scene.scale_to_input``)."""
    out = {**metrics, "units": "input", "scale_to_input": scale}
    for k in ("diagonal", "threshold", "max_dist"):
        if k in out:
            out[k] = out[k] * scale
    for k in ("depth", "rendered_depth"):
        if k in out:
            out[k] = {**out[k], "rmse": out[k]["rmse"] * scale}
    if "chamfer" in out:
        out["chamfer"] = {k: (v * scale if k in ("accuracy", "completeness", "chamfer", "threshold", "max_dist",
                                                 "gt_extent") else v)
                          for k, v in out["chamfer"].items()}
    return out
