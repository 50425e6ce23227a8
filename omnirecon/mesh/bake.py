"""Baked vertex colours: the appearance branch's blend at every mesh vertex, for PLY/GLB export.

Each vertex ``p`` (with area-weighted vertex normal ``n``) is coloured by Omni-Recon's own
image-based blend (``OmniRecon.shade``: ``omega = softmax_i MLP([ReLU(Linear(F_i(p))); u - u_i])``,
colour ``sum_i omega_i c_i(p)``) restricted to its **most frontal visible** source views:

* **visible**: ``p`` projects inside source ``i`` in front of it and passes
  :class:`~omnirecon.mesh.ibr.MeshRenderer`'s occlusion test against the mesh rasterized at
  source ``i`` (z-depth at most ``1 + tol`` times the largest of the four rasterized depths around
  the projection), and source ``i`` faces the vertex: ``n . (c_i - p) > 0``;
* **most frontal**: of those, the ``views`` sources with the largest cosine between ``n`` and the
  direction to the camera centre ``c_i``.

The blend needs a viewing direction ``u``; a baked colour must not depend on one, so the vertex is
looked at along its normal (``u = -n``, the most frontal virtual viewer). A vertex that no source
sees that way (occluded everywhere, facing away from every source, or without a normal) falls back
to every source it projects into (in front, inside the image), and a vertex outside every source
keeps the background colour; :class:`BakeResult` counts both.

The colours are view-independent and interpolated per vertex, so they are a low-pass,
single-direction version of the per-pixel renderer; they are the fallback of the web viewer and
what other programs show of an exported PLY/GLB.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from torch import Tensor

from omnirecon.mesh.files import to_input_frame
from omnirecon.options import check_value
from omnirecon.render.raster import vertex_normals


@dataclass
class BakeOptions:
    """Settings of :func:`bake_vertex_colors`."""

    views: int = 3
    """Most frontal visible source views blended per vertex (the paper renders with 3 sources)."""
    chunk: int = 8192
    """Vertices shaded at once."""

    def check(self) -> None:

        check_value("bake_views", self.views)  # the rules: omnirecon/options.py
        check_value("chunk", self.chunk)


@dataclass
class BakeResult:
    """Per-vertex colours and how they were obtained (``V`` vertices, ``K`` sources)."""

    colors: Tensor
    """Blended RGB in [0, 1]. ``# [V, 3]`` float32 (CPU)"""
    selected: Tensor
    """Sources each vertex blended (the most frontal visible ones, or the fallback). ``# [V, K]`` bool"""
    fallback: int
    """Vertices no source sees frontally and unoccluded: blended from every source they project into."""
    unseen: int
    """Vertices outside every source (in front and inside the image): the background colour."""

    def summary(self) -> dict:
        V = int(self.colors.shape[0])
        return {"vertices": V, "fallback": self.fallback, "unseen": self.unseen,
                "mean_views": float(self.selected.sum(1).float().mean()) if V else 0.0}


def bake_vertex_colors(renderer, vertices, faces, options: BakeOptions | None = None,
                       background=(1.0, 1.0, 1.0)) -> BakeResult:
    """Colour every vertex with the appearance branch's blend of its most frontal visible sources.

    Args:
        renderer: A :class:`~omnirecon.mesh.ibr.MeshRenderer` of this mesh built with
            ``MeshRenderOptions(visibility=True)`` (its source depth maps make the occlusion test and
            its encoded sources are reused); its model needs ``shade(features, points, origins, visible)``.
        vertices: Vertex positions in the sources' (scene) frame. ``# [V, 3]``
        faces: Triangles, for the vertex normals. ``# [F, 3]``
        options: :class:`BakeOptions`.
        background: Colour of vertices no source sees.

    Returns:
        A :class:`BakeResult`.
    """
    options = options or BakeOptions()
    options.check()
    if renderer.source_depth_max is None:
        raise ValueError("bake_vertex_colors needs a MeshRenderer built with MeshRenderOptions(visibility=True)")
    verts = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    normals = torch.from_numpy(vertex_normals(verts, np.asarray(faces, dtype=np.int64).reshape(-1, 3)))
    dev, dt = renderer.device, renderer.dtype
    centers = renderer.sources.cameras.centers.to(dev, torch.float64)  # [K, 3]
    K, V = centers.shape[0], verts.shape[0]
    colors = torch.empty(V, 3, dtype=torch.float32)
    selected = torch.zeros(V, K, dtype=torch.bool)
    fallback = unseen = 0
    bg = torch.as_tensor(background, dtype=torch.float32).reshape(3)
    with torch.inference_mode():
        for s in range(0, V, options.chunk):
            p64 = torch.from_numpy(verts[s:s + options.chunk]).to(dev)  # [n, 3]
            n = normals[s:s + options.chunk].to(dev)  # [n, 3] (zero for unreferenced vertices)
            p = p64.to(dt)
            _, _, visible = renderer.project(p.T.contiguous())  # [K, n]: in front, in image, not occluded
            to_cam = torch.nn.functional.normalize(centers[:, None] - p64[None], dim=-1)  # [K, n, 3]
            cos = (to_cam * n[None]).sum(-1)  # [K, n]
            frontal = visible & (cos > 0)
            score = torch.where(frontal, cos, torch.full_like(cos, -2.0))
            rank = score.argsort(0, descending=True).argsort(0)  # [K, n] 0 = most frontal
            sel = frontal & (rank < options.views)
            none = ~sel.any(0)  # [n]
            if none.any():
                proj = renderer.sources.cameras.project(p)  # the model's own in-front / in-image test
                sel[:, none] = proj.in_image[:, none].to(dev)
            seen = sel.any(0)
            # viewing direction: along -n (looking at the vertex head-on); without a normal, from the
            # most frontal selected source
            has_n = n.norm(dim=-1) > 0.5
            best = torch.where(sel, cos, torch.full_like(cos, -3.0)).argmax(0)  # [n]
            origin = torch.where(has_n[:, None], p64 + n, centers[best])
            out = renderer.model.shade(renderer.features, p, origin.to(dt), visible=sel.T)
            rgb = out["rgb"].float().cpu()
            rgb[~seen.cpu()] = bg
            colors[s:s + options.chunk] = rgb.clamp(0, 1)
            selected[s:s + options.chunk] = sel.T.cpu()
            fallback += int((none & seen).sum())
            unseen += int((~seen).sum())
    return BakeResult(colors, selected, fallback, unseen)


def colored_mesh(vertices, faces, colors: Tensor | np.ndarray, to_input: Tensor | None = None) -> trimesh.Trimesh:
    """A ``trimesh.Trimesh`` with per-vertex RGBA colours (uint8, alpha 255), moved to the input frame by the
    similarity ``to_input # [4, 4]`` when given (:func:`omnirecon.mesh.files.to_input_frame`: winding
    flipped if it mirrors; the vertex order, hence the colours, is kept)."""

    mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64), process=False)
    if to_input is not None:
        mesh = to_input_frame(mesh, torch.as_tensor(to_input))
    rgb = np.asarray(colors.cpu() if isinstance(colors, Tensor) else colors, dtype=np.float64).reshape(-1, 3)
    rgba = np.concatenate([np.round(np.clip(rgb, 0, 1) * 255), np.full((len(rgb), 1), 255.0)], 1).astype(np.uint8)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=rgba)
    return mesh
