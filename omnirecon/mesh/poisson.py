"""Screened Poisson surface reconstruction for object captures (an optional surface stage of the pipeline).

The fused, cleaned mesh's vertices and normals are handed to screened Poisson (Kazhdan & Hoppe 2013,
through ``pymeshlab``: the ``surface`` extra), which closes the holes fusion leaves (textureless roofs,
grazing walls) with a watertight surface. A watertight surface also closes the object's silhouette
where no view saw it, so the result is trimmed by the views' object masks (a visual-hull test:
a vertex projecting outside the dilated mask of a view that sees it is dropped)  (optionally also by
Poisson's own sample density, off by default: the closed holes are exactly the low-density parts). Only with masks: on a scene without them a
watertight surface has no silhouette to trim to.
"""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError
from omnirecon.mesh.clean import outside_votes


def available() -> bool:
    """Whether ``pymeshlab`` imports."""
    try:
        import pymeshlab  # noqa: F401
    except ImportError:
        return False
    return True


def poisson_surface(mesh: trimesh.Trimesh, cameras: Cameras, masks: np.ndarray, depth: int = 9,
                    density_quantile: float = 0.0, max_outside: int = 0) -> tuple[trimesh.Trimesh, dict]:
    """Screened Poisson over ``mesh``'s oriented vertices, trimmed to ``masks`` (module docstring).

    Args:
        mesh: The fused, cleaned mesh (scene frame).
        cameras: The training views the masks belong to.
        masks: Dilated object masks of those views. ``# [N, H, W]`` bool
        depth: Octree depth of the reconstruction (9: 512^3 at the finest level).
        density_quantile: Drop vertices whose Poisson sample density is under this quantile (0: none;
            the holes Poisson closes are exactly the low-density parts, so the masks do the trimming).
        max_outside: Keep vertices outside at most this many views' masks.

    Returns:
        The trimmed surface and a record (vertices in, faces out, faces trimmed).
    """
    try:
        import pymeshlab
    except ImportError as e:
        raise InputError("screened Poisson needs pymeshlab", None,
                         "pip install 'omnirecon[surface]' (or pymeshlab), or use --surface fill") from e
    if len(mesh.vertices) < 100:
        return mesh, {"poisson": "skipped: fewer than 100 vertices"}
    v = np.asarray(mesh.vertices, np.float64)
    n = np.asarray(mesh.vertex_normals, np.float64)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, v_normals_matrix=n))
    ms.generate_surface_reconstruction_screened_poisson(depth=depth, preclean=True, threads=1)
    out = ms.current_mesh()
    pv, pf = out.vertex_matrix(), out.face_matrix()
    density = out.vertex_scalar_array() if out.has_vertex_scalar() else None
    keep_v = outside_votes(pv, cameras.to(dtype=torch.float64), masks) <= max_outside
    if density is not None and density_quantile > 0:
        keep_v &= density >= np.quantile(density, density_quantile)
    keep_f = keep_v[pf].all(1)
    surface = trimesh.Trimesh(pv, pf[keep_f], process=False)
    surface.remove_unreferenced_vertices()
    return surface, {"poisson_depth": depth, "input_vertices": len(v), "poisson_faces": int(len(pf)),
                     "trimmed_faces": int((~keep_f).sum()), "faces": int(len(surface.faces))}
