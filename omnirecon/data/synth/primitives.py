"""Primitive shapes as fine triangle meshes, and per-corner shading normals.

Every primitive is built by :mod:`trimesh.creation` in its *local frame*, centred on the middle of
its bounding box, then placed in the world by a rigid pose. The renderer draws exactly these
triangles, so the exported mesh is the exact geometry of the images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

KINDS = ("sphere", "box", "cylinder", "cone", "capsule", "torus")
"""Primitive types the generator draws from."""


@dataclass
class Primitive:
    """One object of a scene: shape, size, pose and texture."""

    kind: str
    """One of :data:`KINDS`."""
    params: dict
    """Shape parameters in scene units (``radius``, ``height``, ``extents``, ``major``, ``minor``)."""
    pose: np.ndarray
    """Local-to-world rigid transform. ``# [4, 4]`` float64"""
    texture: dict
    """Texture descriptor (see :func:`omnirecon.data.synth.textures.make_texture`)."""
    texture_scale: float
    """Size of one texture tile in local units."""
    id: int
    """Label id of the object in the label images (1..254)."""

    def to_json(self) -> dict:
        return {
            "id": self.id, "type": self.kind,
            "params": {k: (list(map(float, v)) if np.ndim(v) else float(v)) for k, v in self.params.items()},
            "pose": self.pose.tolist(), "texture": self.texture, "texture_scale": self.texture_scale,
        }


def random_params(kind: str, size: float, rng: np.random.Generator) -> dict:
    """Shape parameters for a primitive whose bounding sphere has radius about ``size``."""
    if kind == "sphere":
        return {"radius": size * rng.uniform(0.7, 1.0)}
    if kind == "box":
        e = rng.uniform(0.5, 1.0, 3)
        return {"extents": 2 * size * e / np.linalg.norm(e) * np.sqrt(3) * 0.6}
    if kind in ("cylinder", "cone"):
        return {"radius": size * rng.uniform(0.4, 0.8), "height": size * rng.uniform(0.8, 1.6)}
    if kind == "capsule":
        r = size * rng.uniform(0.3, 0.55)
        return {"radius": r, "height": rng.uniform(0.4, 1.0) * (2 * size - 2 * r)}
    if kind == "torus":
        minor = size * rng.uniform(0.18, 0.35)
        return {"major": size - minor, "minor": minor}
    raise ValueError(f"unknown primitive {kind!r}")


def primitive_mesh(kind: str, params: dict, detail: int = 1) -> trimesh.Trimesh:
    """Closed, outward-facing triangle mesh of a primitive in its local frame (bounding box centred).

    ``detail`` scales the tessellation: 1 gives about 1-5k triangles for curved shapes (2.9 degrees
    between neighbouring sphere facets, 5.6 around cylinders and cones, 11 around a torus tube;
    the sphere deviates from the ideal one by 0.11 % of its radius), 0 a quarter of that, 2 four
    times as many.
    """
    detail = int(np.clip(detail, 0, 2))
    sections = 32 * 2**detail
    if kind == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=3 + detail, radius=params["radius"])
    elif kind == "box":
        mesh = trimesh.creation.box(extents=params["extents"])
    elif kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=params["radius"], height=params["height"], sections=sections)
    elif kind == "cone":
        mesh = trimesh.creation.cone(radius=params["radius"], height=params["height"], sections=sections)
    elif kind == "capsule":
        mesh = trimesh.creation.capsule(height=params["height"], radius=params["radius"],
                                        count=[sections, sections // 2])
    elif kind == "torus":
        mesh = trimesh.creation.torus(params["major"], params["minor"], major_sections=sections,
                                      minor_sections=sections // 2)
    else:
        raise ValueError(f"unknown primitive {kind!r}")
    vertices = mesh.vertices - mesh.bounds.mean(0)
    return trimesh.Trimesh(vertices, mesh.faces, process=False)


def corner_normals(vertices: np.ndarray, faces: np.ndarray, crease_deg: float = 35.0) -> np.ndarray:
    """Smooth shading normals per triangle corner, kept sharp across creases. ``# [F, 3, 3]``

    The normal at corner ``(f, k)`` averages the area-weighted normals of the faces around vertex
    ``faces[f, k]`` that lie within ``crease_deg`` of face ``f``: curved surfaces shade smoothly,
    box edges and cylinder rims stay sharp.

    Args:
        vertices: ``# [V, 3]``
        faces: ``# [F, 3]`` int
    """
    tri = vertices[faces]  # [F, 3, 3]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # [F, 3], |cross| = 2 area
    unit = cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-300)
    corner_vertex = faces.reshape(-1)  # [3F]
    corner_face = np.repeat(np.arange(len(faces)), 3)  # [3F]
    order = np.argsort(corner_vertex, kind="stable")
    degree = np.bincount(corner_vertex, minlength=len(vertices))  # [V]
    first = np.cumsum(degree) - degree  # [V]
    # All (corner a, face b) pairs that share a vertex: sum of degree^2 pairs.
    per_corner = degree[corner_vertex]  # [3F]
    a = np.repeat(np.arange(len(corner_vertex)), per_corner)
    offset = np.arange(len(a)) - np.repeat(np.cumsum(per_corner) - per_corner, per_corner)
    b = corner_face[order[first[corner_vertex[a]] + offset]]
    fa = corner_face[a]
    ok = (unit[fa] * unit[b]).sum(1) >= np.cos(np.radians(crease_deg))
    out = np.zeros((len(corner_vertex), 3))
    for c in range(3):
        out[:, c] = np.bincount(a[ok], weights=cross[b[ok], c], minlength=len(corner_vertex))
    out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)
    return out.reshape(len(faces), 3, 3)


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit geometric normals of triangles (right-hand rule). ``# [F, 3]``"""
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
