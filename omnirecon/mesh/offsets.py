"""``omnirecon finetune --tune surface``: the mesh's vertices moved along their normals by a tuned scalar each.

Rasterization fixes, for a step, which face each pixel sees and where on it (its barycentrics: "fixed
visibility"); the shaded point is then ``p = sum_j b_j (v_j + d_j n_j)``, a differentiable function of the per-vertex
offsets ``d`` (scene units, zero at start) along the start mesh's unit vertex normals ``n``, taken where the pixel's
ray meets that moved face (to first order: the point slides along the ray by the displacement's component along the
face normal over the ray's, :meth:`SurfaceOffsets.shift`), so the pixel keeps its colour target while the point's
projection into each source moves with ``d``: the photometric loss across the sources moves the surface.
Offsets are bounded to ``limit`` times the diagonal of the scene's box (``d = limit * diagonal * tanh(raw)``), so that
the fixed visibility stays close to what rasterizing the moved mesh would give, and smoothed by a Laplacian term (the
mean squared difference of the offsets across each edge, in edge lengths). With ``res`` > 0 the offsets are a coarse
``res``-cube grid over the box sampled trilinearly at each vertex (a dense mesh's vertices then move together: one
pixel's gradient reaches a cell's worth of them), smoothed across the grid's neighbouring cells instead.
"""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from omnirecon.render.raster import vertex_normals


def face_barycentrics(vertices: torch.Tensor, faces: torch.Tensor, face: torch.Tensor,
                      points: torch.Tensor) -> torch.Tensor:
    """Barycentrics of ``points # [P, 3]`` on the triangles ``face # [P]`` (indices into ``faces # [F, 3]`` of
    ``vertices # [V, 3]``), clamped to >= 0 and renormalised. ``# [P, 3]``"""
    a, b, c = vertices[faces[face]].double().unbind(1)  # [P, 3] each
    e0, e1, ep = b - a, c - a, points.double() - a
    d00, d01, d11 = (e0 * e0).sum(-1), (e0 * e1).sum(-1), (e1 * e1).sum(-1)
    d20, d21 = (ep * e0).sum(-1), (ep * e1).sum(-1)
    den = (d00 * d11 - d01 * d01).clamp_min(1e-30)
    v, w = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    bary = torch.stack([1 - v - w, v, w], -1).clamp_min(0)
    return (bary / bary.sum(-1, keepdim=True).clamp_min(1e-12)).float()


GRAZING = 0.25
"""The smallest ``|cos|`` between a ray and the face normal :meth:`SurfaceOffsets.shift` divides by (a grazing ray
would slide a point far along itself for a small offset)."""


class SurfaceOffsets(torch.nn.Module):
    """Per-vertex offsets along the start mesh's vertex normals (``--tune surface``), zero at start."""

    def __init__(self, mesh: trimesh.Trimesh, limit: float, box: torch.Tensor, res: int = 0):
        super().__init__()
        verts, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
        self.register_buffer("vertices", torch.from_numpy(verts).float())  # [V, 3]
        self.register_buffer("faces", torch.from_numpy(faces))  # [F, 3]
        self.register_buffer("normals", torch.from_numpy(vertex_normals(verts, faces)).float())  # [V, 3] unit
        tri = verts[faces]  # [F, 3, 3]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.register_buffer("face_normals", torch.from_numpy(
            fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-20)).float())  # [F, 3] unit
        edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1), axis=0)
        self.register_buffer("edges", torch.from_numpy(edges))  # [E, 2]
        self.edge = float(np.linalg.norm(verts[edges[:, 0]] - verts[edges[:, 1]], axis=1).mean()) if len(edges) else 1.0
        """The mesh's mean edge length (scene units)."""
        box = box.float()
        self.bound = float(limit * (box[1] - box[0]).norm())
        """The largest offset (scene units)."""
        self.register_buffer("cell", ((self.vertices - box[0]) / (box[1] - box[0]).clamp_min(1e-9) * 2 - 1))  # [V, 3]
        self.res = res
        self.raw = torch.nn.Parameter(torch.zeros((len(verts),) if res <= 0 else (1, 1, res, res, res)),
                                      requires_grad=False)
        """Unbounded offsets, per vertex ``# [V]`` or per grid cell ``# [1, 1, R, R, R]`` (z-major): ``d = bound *
        tanh(raw)``."""

    def offsets(self, idx: torch.Tensor | None = None) -> torch.Tensor:
        """Offsets along the normals of the vertices ``idx`` (all when ``None``), scene units. ``# [n]``"""
        d = self.bound * torch.tanh(self.raw)
        if self.res <= 0:
            return d if idx is None else d[idx]
        g = (self.cell if idx is None else self.cell[idx]).reshape(1, 1, 1, -1, 3)
        return torch.nn.functional.grid_sample(d, g, align_corners=True, padding_mode="border").reshape(-1)

    def shift(self, face: torch.Tensor, bary: torch.Tensor, points: torch.Tensor, origins: torch.Tensor,
              base: torch.Tensor | None = None) -> torch.Tensor:
        """How far the points ``# [n, 3]`` seen from ``origins # [n, 3]`` on ``face # [n]`` (-1: not on the mesh, no
        shift) at ``bary # [n, 3]`` move along their rays to the moved face: the displacement ``sum_j b_j d_j n_j``'s
        component along the face normal over the ray's (the ray's at least :data:`GRAZING` in magnitude); with
        ``base # [V]``, the offsets the points were rasterized at, only the offsets' change since. ``# [n, 3]``"""
        on = face >= 0
        f = face.clamp_min(0)
        corners = self.faces[f]  # [n, 3]
        d = self.offsets(corners.reshape(-1)).reshape(corners.shape)  # [n, 3]
        d = (d if base is None else d - base[corners]) * on[:, None]
        disp = ((bary * d)[..., None] * self.normals[corners]).sum(1)  # [n, 3]
        nf = self.face_normals[f]  # [n, 3]
        ray = torch.nn.functional.normalize(points - origins, dim=-1)
        cos = (ray * nf).sum(-1)
        cos = torch.where(cos < 0, cos.clamp(max=-GRAZING), cos.clamp(min=GRAZING))
        return ray * ((disp * nf).sum(-1) / cos)[:, None]

    def smoothness(self) -> torch.Tensor:
        """Mean squared offset difference across the mesh's edges, in mean edge lengths squared (the Laplacian
        term's energy)."""
        if self.res > 0:  # the grid's neighbouring cells
            d = self.bound * torch.tanh(self.raw[0, 0]) / self.edge  # [R, R, R]
            return sum((d.diff(dim=k)).square().mean() for k in range(3)) / 3 if self.res > 1 else d.sum() * 0
        if not len(self.edges):
            return self.raw.new_zeros(())
        d = self.offsets() / self.edge
        return (d[self.edges[:, 0]] - d[self.edges[:, 1]]).square().mean()

    @torch.no_grad()
    def moved(self, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
        """``mesh`` (the start mesh) with its vertices moved by the offsets (faces, colours kept)."""
        out = mesh.copy()
        out.vertices = (self.vertices + self.offsets()[:, None] * self.normals).double().numpy()
        return out
