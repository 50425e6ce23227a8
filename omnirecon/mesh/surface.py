"""One coherent surface from the depth that several views confirm (``MeshOptions.surface = "coherent"``).

Per-view depth fused in a TSDF keeps every view's own mistakes where no other view contradicts them, and the fills
that make each photo's pixels covered are sheets seen from anywhere else. Classical pipelines that users trust work
differently (COLMAP: geometric consistency, then screened Poisson over the fused oriented points; OpenMVS: a graph
cut over them), and so does this stage:

1. **Confirmed oriented points** (:func:`oriented_points`): every pixel whose depth at least ``confirm`` other maps
   agree with (:func:`omnirecon.mesh.fusion.consistency`, the maps' own disagreement as the margin), back-projected,
   with a normal from its neighbours' points (central differences, none across a depth edge), facing its camera.
   Points are averaged per cell of about a voxel (:func:`binned`).
2. **Screened Poisson** (Kazhdan & Hoppe 2013, through ``pymeshlab``; :func:`screened_poisson`): one watertight
   surface through them.
3. **Support** (:func:`supported`): Poisson closes every hole and wraps the points in a watertight hull, so its
   surface is kept only where a view supports it:

   * a face farther than ``reach`` voxels from every confirmed point is not supported: dropped (a bridge across a
     crevice or a textureless patch between confirmed points stays); one no training view sees
     (:func:`omnirecon.mesh.defects.seen_faces`) already beyond ``reach_unseen`` voxels;
   * a vertex some view sees through (a 3x3 pixel block that shows the scene's known background colour: sky, a
     studio backdrop) is dropped;
   * a vertex at least ``free_votes`` views see confirmed depth beyond (by the maps' margin, over the 3x3 pixels
     around its projection: their rays pass through it) and farther than ``reach`` voxels from a confirmed point
     is dropped;
   * what leaves the bounds, pieces smaller than the mesh's ``min_component`` fraction and pieces whose extent is
     under :data:`omnirecon.mesh.defects.MIN_PIECE` of the bounds' diagonal (fragments) go too.

4. **A background layer** (:func:`background_layer`, ``layer`` > 0): the same over the confirmed points within the
   bounds grown by half their extent on each side, at a cell four times as coarse and smoother, set back three voxels
   behind where its points lie. Where the surface has a face the layer is hidden behind it; where it has none (what
   no two views confirmed at the surface's scale, what lies past the bounds: the wall around a mounted head, the
   houses along a street) the layer shows a smooth approximation instead of a hole.

No fill is made: no sheet is built from one view's depth to cover its pixels; a pixel neither the surface nor the
layer covers is the renderer's (its far layer or nearest fill).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError


@dataclass
class SurfaceOptions:
    """Settings of the coherent surface."""

    confirm: int = 1
    """Other depth maps that must agree with a pixel's depth (:func:`omnirecon.mesh.fusion.consistency`) before its
    point enters the surface."""
    normal_step: int = 2
    """Pixels on each side of a pixel whose back-projected points give its normal (central differences)."""
    edge: float = 0.03
    """A neighbour whose depth differs from the pixel's by more than this fraction marks a depth edge: the pixel gets
    no normal and gives no point."""
    cell: float = 1.0
    """Points are averaged per cubic cell of this many voxels before Poisson."""
    octree: int = 0
    """Screened Poisson's octree depth (0: the depth whose finest cell is about two voxels over the points' extent,
    within 6-10)."""
    point_weight: float = 4.0
    """Screened Poisson's screening weight: how closely the surface follows the points against its smoothness."""
    reach: float = 16.0
    """Voxels: surface farther than this from every confirmed point is not supported (module docstring)."""
    reach_unseen: float = 4.0
    """Voxels: surface no training view sees, or that views see past, farther than this from every confirmed point is
    not supported."""
    carve_background: bool = True
    """Drop surface some view sees through: the scene's known background colour, or confirmed depth past the
    bounds."""
    free_votes: int = 2
    """Views that must see confirmed depth beyond a vertex (farther than ``reach`` from a confirmed point) to drop
    it; 0 = off."""
    fine: str = "poisson"
    """The surface: ``poisson`` (screened Poisson over the confirmed points, kept where views support it) or ``tsdf``
    (the fused TSDF surface of every pixel's depth, weighted by its confidence and agreement, cleaned, less its
    fragments): hard materials (dark, shiny) whose depth two views seldom confirm keep more surface with it."""
    layer: float = 4.0
    """The background layer's cell, in voxels (0: no layer): a coarse, smooth surface over every confirmed point
    within the grown bounds, set back behind the surface, which shows where the surface has no face (what no two views
    confirmed, what lies past the bounds: a wall around an object, the houses along a street)."""
    layer_grow: float = 0.5
    """The background layer takes points within the bounds grown by this fraction of their extent on each side."""
    layer_behind: float = 3.0
    """Voxels the background layer is set back behind where its points lie."""
    threads: int = 1
    """Threads of the Poisson solver."""

    def check(self) -> None:
        if self.confirm < 1 or self.normal_step < 1 or self.free_votes < 0:
            raise InputError(f"confirm and normal_step must be >= 1 and free_votes >= 0, got {self.confirm}, "
                             f"{self.normal_step}, {self.free_votes}", None, "use e.g. 1, 2 and 2")
        if not all(v > 0 for v in (self.edge, self.cell, self.point_weight, self.reach, self.reach_unseen)) or \
                not all(math.isfinite(v) for v in (self.edge, self.cell, self.point_weight)):
            raise InputError(f"edge, cell, point_weight, reach and reach_unseen must be > 0, got {self.edge}, "
                             f"{self.cell}, {self.point_weight}, {self.reach}, {self.reach_unseen}", None,
                             "use e.g. 0.03, 1, 4, 16 and 4")
        if self.octree != 0 and not 4 <= self.octree <= 12:
            raise InputError(f"octree must be 0 (automatic) or in 4-12, got {self.octree}", None, "use 0")
        if self.fine not in ("poisson", "tsdf"):
            raise InputError(f"fine must be poisson or tsdf, got {self.fine!r}", None, "use fine='poisson'")
        if self.threads < 1:
            raise InputError(f"threads must be >= 1, got {self.threads}", None, "use e.g. 1")


def oriented_points(cameras: Cameras, depths: Tensor, keep: Tensor, step: int = 2,
                    edge: float = 0.03) -> tuple[Tensor, Tensor]:
    """World points and unit normals of the pixels ``keep # [N, H, W]`` of the z-depth maps ``depths # [N, H, W]``
    (0 = none) that have a normal: the cross product of the central differences of the back-projected points ``step``
    pixels away, where those four neighbours have depth within ``edge`` (relative) of the pixel's; the normal faces
    the pixel's camera. ``# [P, 3]`` float64 each"""
    cams = cameras.to(dtype=torch.float64)
    pts, nrm = [], []
    s = step
    for i in range(len(cams)):
        z = depths[i].double()
        H, W = z.shape
        if H <= 2 * s or W <= 2 * s:
            continue
        o, d = cams[i].image_rays(normalize=False)
        P = (o + d * z[None, ..., None])[0]  # [H, W, 3]
        zc = z[s:-s, s:-s]
        ok = (zc > 0) & keep[i, s:-s, s:-s]
        for nb in (z[s:-s, 2 * s:], z[s:-s, :-2 * s], z[2 * s:, s:-s], z[:-2 * s, s:-s]):
            ok &= (nb > 0) & ((nb - zc).abs() <= edge * zc)
        if not ok.any():
            continue
        n = torch.linalg.cross(P[s:-s, 2 * s:] - P[s:-s, :-2 * s], P[2 * s:, s:-s] - P[:-2 * s, s:-s])  # [h, w, 3]
        p, n = P[s:-s, s:-s][ok], n[ok]
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-18)
        n = torch.where(((cams.centers[i] - p) * n).sum(-1, keepdim=True) < 0, -n, n)  # facing the camera
        pts.append(p)
        nrm.append(n)
    if not pts:
        return torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.float64)
    return torch.cat(pts), torch.cat(nrm)


def binned(points: Tensor, normals: Tensor, cell: float) -> tuple[Tensor, Tensor, Tensor]:
    """Points averaged per cubic cell of side ``cell`` (normals summed, then normalised), with the number of points
    in each cell. ``# [C, 3]``, ``# [C, 3]``, ``# [C]``"""
    if len(points) == 0:
        return points, normals, torch.zeros(0)
    key = torch.floor((points - points.min(0).values) / cell).long()  # [P, 3]
    _, inverse, counts = torch.unique(key, dim=0, return_inverse=True, return_counts=True)
    C = len(counts)
    p = torch.zeros(C, 3, dtype=points.dtype).index_add_(0, inverse, points) / counts[:, None]
    n = torch.zeros(C, 3, dtype=normals.dtype).index_add_(0, inverse, normals)
    good = n.norm(dim=-1) > 1e-9  # opposite normals cancel: a cell straddling a thin wall's two sides
    return p[good], n[good] / n[good].norm(dim=-1, keepdim=True), counts[good]


def octree_depth(points: Tensor, voxel: float) -> int:
    """The octree depth whose finest cell is about two voxels over the extent of ``points``, within 6-10."""
    extent = float((points.max(0).values - points.min(0).values).max()) if len(points) else voxel
    return int(np.clip(math.ceil(math.log2(max(extent / (2 * voxel), 1.0))), 6, 10))


def screened_poisson(points: Tensor, normals: Tensor, depth: int, point_weight: float = 4.0,
                     threads: int = 1) -> trimesh.Trimesh:
    """Screened Poisson surface (pymeshlab) through oriented ``points # [P, 3]``, octree ``depth``."""
    try:
        import pymeshlab
    except ImportError as e:
        raise InputError("the coherent surface needs pymeshlab", None,
                         "pip install 'omnirecon[surface]' (or pymeshlab), or use --surface fusion") from e
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=points.numpy().astype(np.float64),
                               v_normals_matrix=normals.numpy().astype(np.float64)))
    ms.generate_surface_reconstruction_screened_poisson(depth=depth, pointweight=point_weight, preclean=True,
                                                        threads=threads)
    out = ms.current_mesh()
    return trimesh.Trimesh(out.vertex_matrix(), out.face_matrix(), process=False)


def view_votes(vertices: Tensor, cameras: Cameras, depths: Tensor, rel: float, empty: Tensor | None) -> tuple[Tensor, Tensor]:
    """Per vertex: how many views see confirmed depth beyond it (the 3x3 pixels around its projection all hold depth
    more than ``rel`` farther, or see through), and how many see through it: ``empty # [N, H, W]`` at all 9 pixels.
    ``depths # [N, H, W]``: confirmed depth, 0 = none. ``# [V]`` int64 each"""
    cams = cameras.to(dtype=torch.float64)
    N, H, W = depths.shape
    past = torch.zeros(len(vertices), dtype=torch.long)
    sky = torch.zeros(len(vertices), dtype=torch.long)
    far = torch.full((), float("inf"), dtype=torch.float64)
    for i in range(N):
        p = cams[i].project(vertices)
        uv, z = p.uv[0], p.depth[0]
        col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        inside = p.in_image[0] & (col >= 1) & (row >= 1) & (col < W - 1) & (row < H - 1) & (z > 0)
        d = depths[i].double()
        e = empty[i] if empty is not None else torch.zeros_like(d, dtype=torch.bool)
        least = torch.full_like(z, float("inf"))
        all_sky = torch.ones_like(inside)
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                r, c = (row + dr).clamp(0, H - 1), (col + dc).clamp(0, W - 1)
                v = torch.where(e[r, c], far, torch.where(d[r, c] > 0, d[r, c], torch.zeros_like(z)))
                least = torch.minimum(least, torch.where(v > 0, v, torch.zeros_like(v)))
                all_sky &= e[r, c]
        past += (inside & (least > z * (1 + rel))).long()
        sky += (inside & all_sky).long()
    return past, sky


def supported(mesh: trimesh.Trimesh, points: Tensor, voxel: float, cameras: Cameras, confirmed: Tensor, rel: float,
              see_through: Tensor | None, options: SurfaceOptions) -> tuple[np.ndarray, dict]:
    """Faces of the Poisson ``mesh`` a view supports (module docstring, 3): ``# [F]`` bool, and the counts of what
    each rule dropped."""
    from scipy.spatial import cKDTree

    from omnirecon.mesh.defects import seen_faces

    V = torch.from_numpy(np.asarray(mesh.vertices, np.float64))
    faces = np.asarray(mesh.faces)
    far = max(options.reach, options.reach_unseen) * voxel
    dist, _ = cKDTree(points.numpy()).query(V.numpy(), k=1, distance_upper_bound=2 * far if math.isfinite(far) else np.inf)
    near_v = dist <= options.reach_unseen * voxel  # [V]
    unsupported = (dist > options.reach * voxel)[faces].all(1)
    unseen = ~seen_faces(mesh, cameras) & ~near_v[faces].any(1) & ~unsupported
    past, sky = view_votes(V, cameras, confirmed, rel, see_through if options.carve_background else None)
    drop_v = (sky >= 1).numpy()
    if options.free_votes > 0:
        drop_v |= (past >= options.free_votes).numpy() & ~near_v
    carved = drop_v[faces].any(1) & ~unseen & ~unsupported
    keep = ~unseen & ~carved & ~unsupported
    return keep, {"unsupported": int(unsupported.sum()), "unseen_far": int(unseen.sum()), "seen_through": int(carved.sum())}


def confirmed_points(cameras: Cameras, depths: Tensor, confirmed: Tensor, box: Tensor,
                     options: SurfaceOptions) -> tuple[Tensor, Tensor]:
    """:func:`oriented_points` of the ``confirmed`` pixels whose points lie inside ``box # [2, 3]``."""
    points, normals = oriented_points(cameras, depths, confirmed, options.normal_step, options.edge)
    inside = ((points >= box[0].double()) & (points <= box[1].double())).all(-1)
    return points[inside], normals[inside]


def trimmed_poisson(points: Tensor, normals: Tensor, voxel: float, box: Tensor, cameras: Cameras, confirmed: Tensor,
                    rel: float, see_through: Tensor | None, options: SurfaceOptions, min_component: float,
                    record: dict, prefix: str = "") -> trimesh.Trimesh:
    """Screened Poisson over ``points`` binned at ``voxel``, kept where :func:`supported` and inside ``box``, without
    small components and fragments; ``record`` gets the counts and seconds (keys after ``prefix``)."""
    from omnirecon.mesh import clean
    from omnirecon.mesh.defects import MIN_PIECE, small_pieces

    t = time.perf_counter()
    cells, cell_normals, _ = binned(points, normals, options.cell * voxel)
    depth = options.octree or octree_depth(cells, voxel)
    mesh = screened_poisson(cells, cell_normals, depth, options.point_weight, options.threads)
    record.update({f"{prefix}cells": len(cells), f"{prefix}octree": depth, f"{prefix}poisson_faces": len(mesh.faces),
                   f"{prefix}seconds_poisson": time.perf_counter() - t})
    t = time.perf_counter()
    lo, hi = box[0].double().numpy(), box[1].double().numpy()
    in_box = ((mesh.vertices >= lo) & (mesh.vertices <= hi)).all(1)
    keep, dropped = supported(mesh, points, voxel, cameras, confirmed, rel, see_through, options)
    mesh = clean.keep_faces(mesh, keep & in_box[mesh.faces].all(1))
    mesh = clean.drop_small_components(mesh, min_component)
    mesh = clean.keep_faces(mesh, ~small_pieces(mesh, MIN_PIECE * float(np.linalg.norm(hi - lo))))
    record.update({**{f"{prefix}{k}": v for k, v in dropped.items()}, f"{prefix}faces": len(mesh.faces),
                   f"{prefix}seconds_support": time.perf_counter() - t})
    return mesh


def behind(mesh: trimesh.Trimesh, distance: float) -> trimesh.Trimesh:
    """``mesh`` with every vertex moved ``distance`` against its normal (Poisson's normals face the cameras)."""
    if len(mesh.faces) == 0:
        return mesh
    return trimesh.Trimesh(np.asarray(mesh.vertices) - distance * np.asarray(mesh.vertex_normals), mesh.faces,
                           process=False)


def coherent_surface(cameras: Cameras, depths: Tensor, agree: Tensor, voxel: float, rel: float, bounds: Tensor,
                     see_through: Tensor | None = None, options: SurfaceOptions | None = None,
                     min_component: float = 0.001, fused: trimesh.Trimesh | None = None) -> tuple[trimesh.Trimesh, dict]:
    """The coherent surface (module docstring) of the z-depth maps ``depths # [N, H, W]`` (0 = none; depth outside
    the bounds included: the surface takes the points inside them, the background layer those of the grown bounds,
    and both take free space from all) at ``cameras``, given :func:`omnirecon.mesh.fusion.consistency`'s counts
    ``agree # [N, H, W]`` (at margin ``rel``), the voxel size, the scene ``bounds # [2, 3]`` and the pixels that show
    the known background colour ``see_through # [N, H, W]`` (or ``None``). With ``options.layer`` the background
    layer's faces follow the surface's. Returns the mesh (scene frame) and a record (points, octree depths, faces
    after each step, seconds; ``surface_faces``: the surface's faces, which come first). With ``options.fine ==
    "tsdf"`` the surface is ``fused`` (the fused TSDF surface, cleaned), less its fragments, instead of Poisson's."""
    from omnirecon.mesh import clean
    from omnirecon.mesh.defects import MIN_PIECE, small_pieces

    options = options or SurfaceOptions()
    options.check()
    t = time.perf_counter()
    confirmed = (agree >= options.confirm) & (depths > 0)
    points, normals = confirmed_points(cameras, depths, confirmed, bounds, options)
    record = {"confirmed_pixels": float(confirmed.float().mean()), "points": len(points),
              "seconds_points": time.perf_counter() - t}
    if fused is not None:
        mesh = clean.keep_faces(fused, ~small_pieces(fused, MIN_PIECE * float((bounds[1] - bounds[0]).double().norm())))
    elif len(points) < 100:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int), process=False), \
            {**record, "skipped": "fewer than 100 confirmed points", "surface_faces": 0}
    else:
        mesh = trimmed_poisson(points, normals, voxel, bounds, cameras, torch.where(confirmed, depths.double(), 0.0),
                               rel, see_through, options, min_component, record)
    record["surface_faces"] = len(mesh.faces)
    if options.layer > 0:
        layer = background_layer(cameras, depths, agree, voxel, rel, bounds, see_through, options, min_component,
                                 record)
        mesh = trimesh.util.concatenate([mesh, layer]) if len(layer.faces) else mesh
    return mesh, record


def background_layer(cameras: Cameras, depths: Tensor, agree: Tensor, voxel: float, rel: float, bounds: Tensor,
                     see_through: Tensor | None, options: SurfaceOptions, min_component: float,
                     record: dict) -> trimesh.Trimesh:
    """The background layer (module docstring): a coarse surface over the confirmed points inside the bounds grown by
    ``options.layer_grow`` of their extent on each side, cells ``options.layer`` voxels wide, kept where views support
    it (``reach`` in those cells), set ``options.layer_behind`` voxels back."""
    from dataclasses import replace

    lo, hi = bounds[0].double(), bounds[1].double()
    grow = options.layer_grow * (hi - lo)
    box = torch.stack([lo - grow, hi + grow])
    confirmed = (agree >= options.confirm) & (depths > 0)
    points, normals = confirmed_points(cameras, depths, confirmed, box, options)
    if len(points) < 100:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int), process=False)
    coarse = options.layer * voxel
    layer = trimmed_poisson(points, normals, coarse, box, cameras, torch.where(confirmed, depths.double(), 0.0), rel,
                            see_through, replace(options, octree=0, point_weight=1.0), min_component, record, "layer_")
    return behind(layer, options.layer_behind * voxel)


