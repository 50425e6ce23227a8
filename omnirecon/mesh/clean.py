"""Cleaning and the face budget: the stages of the mesh pipeline after marching cubes.

* :func:`mask_votes`: with object masks, keep vertices inside the (dilated) masks of at least
  ``min_views`` views (VolRecon's ``count > 1`` of 3).
* :func:`hull_trim`: with object masks, drop faces outside the visual hull: vertices that fall outside
  the (lightly dilated) masks of more than a given number of the views that see them in frame.
* :func:`visible_faces`: drop faces that no (in-mask) pixel sample of the views hits first. The
  views are rasterised (both sides of every face) at a few samples per voxel edge, by OpenGL
  (``MeshRasterizer``) when it is there; :func:`grow_faces` restores the sliver faces between kept
  faces that the samples miss.
* :func:`drop_small_components`: connected components under a fraction of the largest.
* :func:`decimate`: the face budget (quadric edge collapse, fast-simplification).

What the training views see is never lost for good: the completion stage
(:mod:`omnirecon.mesh.complete`) covers every pixel the cleaned mesh leaves uncovered.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import trimesh

from omnirecon.cameras import Cameras


def dilate_masks(masks: np.ndarray, diameter: float) -> np.ndarray:
    """Binary dilation of ``masks # [N, H, W]`` by a disk of ``diameter`` pixels (< 2: unchanged)."""
    from scipy.ndimage import binary_dilation

    r = diameter / 2
    if r < 1:
        return masks
    k = int(math.floor(r))
    yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
    disk = (xx**2 + yy**2) <= r * r
    return np.stack([binary_dilation(m, structure=disk) for m in masks])


def mask_votes(points: np.ndarray, cameras: Cameras, masks: np.ndarray) -> np.ndarray:
    """Number of views whose mask holds the projection of each point (outside the image: no vote). ``# [P]``"""
    proj = cameras.project(torch.from_numpy(points).to(cameras.c2w))
    col = proj.uv[..., 0].floor().long().clamp(0, cameras.width - 1).numpy()  # [N, P]
    row = proj.uv[..., 1].floor().long().clamp(0, cameras.height - 1).numpy()
    inside = proj.in_image.numpy()
    hit = masks[np.arange(len(masks))[:, None], row, col] & inside
    return hit.sum(0)


def hull_trim(mesh: trimesh.Trimesh, cameras: Cameras, masks: np.ndarray, misses: int) -> trimesh.Trimesh:
    """``mesh`` without the faces that have a vertex whose projection lies in frame but outside the mask
    (``masks # [N, H, W]`` bool) of more than ``misses`` of ``cameras``: the visual hull of the masks, with
    ``misses`` views of slack for a mask that cuts a thin part off. A surface the object really has lies
    inside every view's silhouette, so only floating or fattened surface goes."""
    if len(mesh.faces) == 0:
        return mesh
    return keep_faces(mesh, hull_keep(mesh, cameras, masks, misses))


def hull_keep(mesh: trimesh.Trimesh, cameras: Cameras, masks: np.ndarray, misses: int) -> np.ndarray:
    """The faces :func:`hull_trim` keeps. ``# [F]`` bool"""
    if len(mesh.faces) == 0:
        return np.zeros(0, dtype=bool)
    outside = outside_votes(np.asarray(mesh.vertices), cameras.to(dtype=torch.float64), masks)
    return (outside <= misses)[mesh.faces].all(1)


def restore_seen(mesh: trimesh.Trimesh, keep: np.ndarray, cameras: Cameras, masks: np.ndarray) -> np.ndarray:
    """``keep # [F]`` (bool, e.g. :func:`hull_keep`) plus every face that some view of ``cameras`` sees first at a
    pixel of its mask (``masks # [N, H, W]`` bool, undilated) that the kept faces leave uncovered: a trim never
    deletes surface the training views see and nothing else covers (dtu_scan37's completed mesh lost a few per cent
    of some training views' masks to the visual-hull trim). Both sides of every face are rasterized. ``# [F]`` bool"""
    from omnirecon.render.raster import MeshRasterizer

    keep = keep.copy()
    if len(mesh.faces) == 0 or keep.all():
        return keep
    kept = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    with MeshRasterizer.from_trimesh(mesh, cull_back_faces=False) as full, \
            MeshRasterizer.from_trimesh(kept, cull_back_faces=False) as part:
        for i in range(len(cameras)):
            face = full.rasterize(cameras[i], normals="none").face.numpy()  # [H, W], -1: no face
            hole = masks[i] & (part.rasterize(cameras[i], normals="none").face.numpy() < 0) & (face >= 0)
            keep[np.unique(face[hole])] = True
    return keep


def outside_votes(points: np.ndarray, cameras: Cameras, masks: np.ndarray) -> np.ndarray:
    """Number of views in which each point projects inside the image but outside the mask. ``# [P]``"""
    proj = cameras.project(torch.from_numpy(points).to(cameras.c2w))
    col = proj.uv[..., 0].floor().long().clamp(0, cameras.width - 1).numpy()  # [N, P]
    row = proj.uv[..., 1].floor().long().clamp(0, cameras.height - 1).numpy()
    inside = proj.in_image.numpy() & (proj.depth.numpy() > 0)
    hit = masks[np.arange(len(masks))[:, None], row, col]
    return (inside & ~hit).sum(0)


def keep_faces(mesh: trimesh.Trimesh, keep: np.ndarray) -> trimesh.Trimesh:
    """The faces ``keep # [F]`` (bool) of ``mesh`` with unreferenced vertices removed."""
    out = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    out.remove_unreferenced_vertices()
    return out


def visible_faces(mesh: trimesh.Trimesh, cameras: Cameras, masks: np.ndarray | None, supersample: int = 2) -> np.ndarray:
    """Faces hit first by some (in-mask) pixel sample of ``cameras``, ``supersample``^2 samples per
    pixel. ``# [F]`` bool"""
    from omnirecon.render.raster import MeshRasterizer, gl_available

    seen = np.zeros(len(mesh.faces), dtype=bool)
    rast = MeshRasterizer.from_trimesh(mesh, cull_back_faces=False) if gl_available() else None
    try:
        for i in range(len(cameras)):
            cam = cameras[i].rescaled(supersample) if supersample != 1 else cameras[i]
            if rast is not None:
                face = rast.face_ids(cam)  # the G-buffer's face ids alone
            else:
                from omnirecon.mesh.geometry import rasterize_mesh

                face = rasterize_mesh(np.asarray(mesh.vertices, dtype=np.float64), mesh.faces, cam).face
            if masks is not None:
                face = np.where(np.repeat(np.repeat(masks[i], supersample, 0), supersample, 1), face, -1)
            seen[np.unique(face[face >= 0])] = True
    finally:
        if rast is not None:
            rast.close()
    return seen


def grow_faces(mesh: trimesh.Trimesh, keep: np.ndarray, rings: int = 1) -> np.ndarray:
    """``keep # [F]`` grown by ``rings`` rings of faces sharing an edge's two vertices with kept faces
    (sliver faces between kept faces are often missed by the visibility samples). ``# [F]`` bool"""
    faces = np.asarray(mesh.faces)
    keep = keep.copy()
    for _ in range(rings):
        on = np.zeros(len(mesh.vertices), dtype=bool)
        on[faces[keep].reshape(-1)] = True
        keep |= on[faces].sum(1) >= 2
    return keep


def drop_small_components(mesh: trimesh.Trimesh, fraction: float) -> trimesh.Trimesh:
    """Keep connected components (by shared edges) with at least ``fraction`` of the largest one's faces."""
    if len(mesh.faces) == 0 or fraction <= 0:
        return mesh
    groups = trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(mesh.faces)), min_len=1)
    sizes = np.array([len(g) for g in groups])
    keep = np.zeros(len(mesh.faces), dtype=bool)
    for g in (g for g, n in zip(groups, sizes) if n >= fraction * sizes.max()):
        keep[g] = True
    return keep_faces(mesh, keep)


def weld(vertices: np.ndarray, faces: np.ndarray, keep_faces: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The same triangles over shared vertices: vertices at the same position (bit for bit) become one, and the faces
    this leaves with a repeated corner (zero area: they cover no pixel) are dropped (with ``keep_faces``: kept, so
    that every face keeps its index). The surface drawn is unchanged;
    what changes is that neighbouring faces which only touched now share their corners, as completion's pixel fills
    do (:func:`omnirecon.mesh.complete.pixel_grid_surface` gives each pixel its own four corners, equal to its
    neighbours' where their depths agree), so an edge collapse merges them instead of deleting each pixel's quad as a
    border of its own. ``(vertices # [V', 3], faces # [F', 3])``"""
    vertices, faces = np.ascontiguousarray(vertices), np.asarray(faces)
    if not len(faces):
        return vertices, faces
    rows = vertices.view(np.dtype((np.void, vertices.dtype.itemsize * 3))).reshape(-1)  # [V]: a row's bytes, one key
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)  # (half the time of axis=0)
    unique = vertices[first]  # [V', 3]
    f = inverse.reshape(-1)[faces]  # [F, 3]
    if keep_faces:
        return unique, f
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    return unique, f[keep]


DECIMATORS = ("fast", "meshlab")
"""The quadric edge collapses :func:`decimate` runs: ``fast``, fast-simplification's; ``meshlab``, MeshLab's (pymeshlab,
several times slower; its checks on the faces' shape and normals keep more of some meshes at the same count, lose more
of others: :func:`omnirecon.engine.lod.choose_level_of_detail` measures it per mesh)."""


def decimate(mesh: trimesh.Trimesh, max_faces: int, method: str = "fast") -> trimesh.Trimesh:
    """``mesh`` with at most ``max_faces`` faces (quadric edge collapse, ``method`` of :data:`DECIMATORS`); unchanged
    when it already fits or ``max_faces`` is 0. Where fast-simplification stops above the budget (its checks against
    flipping faces can refuse every collapse left, e.g. on a pixel grid of :func:`weld`-ed fills), MeshLab's quadric
    edge collapse (pymeshlab), slower, takes the mesh the rest of the way."""
    if max_faces <= 0 or len(mesh.faces) <= max_faces:
        return mesh
    if method not in DECIMATORS:
        raise ValueError(f"unknown decimator {method!r}; use one of {DECIMATORS}")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    v, f = verts, faces
    if method == "fast":
        import fast_simplification

        target = 1.0 - max_faces / len(faces)
        for _ in range(4):  # the library stops near the target; tighten until the budget holds
            v, f = fast_simplification.simplify(verts, faces, target_reduction=min(target, 0.999))
            if len(f) <= max_faces:
                break
            target = 1.0 - (1.0 - target) * max_faces / len(f) * 0.98
    if len(f) > max_faces:
        import pymeshlab

        meshes = pymeshlab.MeshSet()
        meshes.add_mesh(pymeshlab.Mesh(v, f))
        meshes.meshing_decimation_quadric_edge_collapse(targetfacenum=max_faces)
        v, f = meshes.current_mesh().vertex_matrix(), meshes.current_mesh().face_matrix()
    out = trimesh.Trimesh(v, f, process=False)
    out.remove_unreferenced_vertices()
    return out


def close_small_holes(mesh: trimesh.Trimesh, max_edges: int) -> tuple[trimesh.Trimesh, int]:
    """``mesh`` with every hole whose boundary is a simple loop of at most ``max_edges`` edges closed by a fan
    around the loop's centroid (wound like the faces around it), and the number of holes closed. Marching
    cubes leaves such pinholes where a voxel corner went unobserved; the mesh path showed them as background
    specks on the demo's ground."""
    if max_edges < 3 or len(mesh.faces) == 0:
        return mesh, 0
    faces = np.asarray(mesh.faces, dtype=np.int64)
    n = len(mesh.vertices)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])  # directed, as the faces wind
    border = e[~np.isin(e[:, 0] * n + e[:, 1], e[:, 1] * n + e[:, 0])]  # no face on the other side
    starts, counts = np.unique(border[:, 0], return_counts=True)
    nxt = dict(zip(border[:, 0].tolist(), border[:, 1].tolist()))
    simple = set(starts[counts == 1].tolist())  # one border edge leaves the vertex: the loop is unambiguous
    done: set[int] = set()
    loops = []
    for a in simple:
        if a in done:
            continue
        loop, v = [a], nxt[a]
        while v != a and v in simple and v not in done and len(loop) <= max_edges:
            loop.append(v)
            v = nxt[v]
        done.update(loop)
        if v == a and 3 <= len(loop) <= max_edges:
            loops.append(loop)
    if not loops:
        return mesh, 0
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    centres = np.stack([verts[lp].mean(0) for lp in loops])
    new = []
    for k, lp in enumerate(loops):
        c = n + k
        new += [(lp[(i + 1) % len(lp)], lp[i], c) for i in range(len(lp))]  # reversed border edge: same winding
    out = trimesh.Trimesh(np.concatenate([verts, centres]), np.concatenate([faces, np.array(new, dtype=np.int64)]),
                          process=False)
    return out, len(loops)


def close_holes(mesh: trimesh.Trimesh, max_edges: int, cpu_seconds: float = 60.0,
                record: dict | None = None) -> tuple[trimesh.Trimesh, int]:
    """``mesh`` with every hole of at most ``max_edges`` boundary edges closed, and the number of faces added.

    With pymeshlab (the ``surface`` extra): its non-manifold edge repair, then its hole closing, which also
    closes holes whose boundary passes a vertex twice (most of fusion's holes beside outlines; the simple-loop
    closer found 76 of the demo mesh's 294 boundaries), in a child process limited to ``cpu_seconds`` of CPU
    time (:mod:`omnirecon.mesh.meshlab_holes`: pymeshlab's hole closing once ran for more than ten CPU-minutes
    on a fused mesh). Without pymeshlab, or when the child runs out of time or fails: :func:`close_small_holes`.
    ``record`` (optional) gets ``closer`` (``"pymeshlab"`` or ``"simple loops"``) and, when pymeshlab ran, its
    ``outcome``, ``cpu_seconds`` and ``timed_out``."""
    if len(mesh.faces) == 0 or max_edges < 3:
        return mesh, 0
    import importlib.util

    closed = None
    if importlib.util.find_spec("pymeshlab") is not None:
        from omnirecon.mesh.meshlab_holes import close_in_child

        child: dict = {}
        closed = close_in_child(np.asarray(mesh.vertices), np.asarray(mesh.faces), max_edges, cpu_seconds, child)
        if record is not None:
            record.update(child, timed_out=child["outcome"] == "out of time")
    if closed is None:
        out, _ = close_small_holes(mesh, max_edges)
    else:
        out = trimesh.Trimesh(closed[0], closed[1], process=False)
    if record is not None:
        record["closer"] = "simple loops" if closed is None else "pymeshlab"
    return out, len(out.faces) - len(mesh.faces)


def clean_mesh(mesh: trimesh.Trimesh, cameras: Cameras, masks: np.ndarray | None, options, supersample: int = 2,
               stages: dict | None = None) -> tuple[trimesh.Trimesh, dict]:
    """Mask votes (with ``masks``, already dilated, ``# [N, H, W]`` bool), hidden faces
    (``options.cull_hidden``, grown by ``options.grow_rings``) and small components, against
    ``cameras``. Returns the mesh and the face count after each step (``stages`` gets the meshes)."""
    counts = {}
    cams = cameras.to(dtype=torch.float64)
    if masks is not None and len(mesh.faces):
        votes = mask_votes(np.asarray(mesh.vertices), cams, masks)
        mesh = keep_faces(mesh, (votes >= min(options.min_views, len(cams)))[mesh.faces].all(1))
        counts["in_masks"] = len(mesh.faces)
        if stages is not None:
            stages["in_masks"] = mesh
    if options.cull_hidden and len(mesh.faces):
        if options.max_faces and len(mesh.faces) > 4 * options.max_faces:  # the test's cost follows the faces
            mesh = decimate(mesh, 2 * options.max_faces)
            counts["pre_decimated"] = len(mesh.faces)
        seen = visible_faces(mesh, cams, masks, supersample)
        mesh = keep_faces(mesh, grow_faces(mesh, seen, options.grow_rings))
        counts["visible"] = len(mesh.faces)
        if stages is not None:
            stages["visible"] = mesh
    mesh = drop_small_components(mesh, options.min_component)
    counts["components"] = len(mesh.faces)
    if stages is not None:
        stages["components"] = mesh
    return mesh, counts
