"""Complete surfaces: every pixel of every training view gets a surface (the last stage of the mesh pipeline).

After fusion and cleaning, each training view is rasterised (OpenGL when there) against the mesh
built so far; the pixels it leaves uncovered, where the photo has content, get a *fill surface* from
that view's own depth:

1. the depth source's map of the view where it has depth (a pixel fusion dropped: low confidence,
   no second view to confirm it, outside the bounds),
2. for forward-facing and unbounded scenes, depth past the bounds box clamped onto the box's far
   side (a backdrop, which raised fern's held-out whole image: stereo.md), and pixels without any
   depth placed on that backdrop,
3. otherwise the nearest known depth (the mesh's or the map's) in the image: hole filling.

The fill of a view is two triangles per uncovered pixel whose corners lie on the rays of image points
offset by a quarter pixel, so each pixel centre lies strictly inside one of its two triangles whatever
the depths are: the view's coverage becomes 100 % by construction. Neighbouring pixels share corner
depths only where their depths agree, so no sheet is stretched across a depth edge (such sheets,
seen from the other views, hid real surface). Views are
completed in turn, each against the mesh plus the fills before it, so overlapping holes are filled
once.

Forward-facing scenes get two more rules:

* **No fill hides what another view sees** (:func:`occluding`): a fill point nearer than the surface some
  other view sees along its ray goes to the backdrop. On fern such fills (from the views' own unconfirmed
  stereo depth) covered part of the held-out pixels and doubled their error: completion lowered the
  whole image; with the rule it raises it.
* **A backdrop layer** (:func:`backdrop_sheet`): a coarse surface on the bounds' far side over every view
  grown by 10 %, behind everything, for the rays that miss every other surface: gaps seen from between
  the views and what lies past the training views' borders (fern: every held-out pixel covered).

"Where the photo has content": inside the (dilated) object masks when the mesh was cleaned with masks;
everywhere on forward-facing scenes; elsewhere, the pixels where the depth source saw a surface
(holes in that set closed), so an empty background stays empty.
"""

from __future__ import annotations

import numpy as np
import torch
import trimesh
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.mesh.clean import weld


class DepthRenderer:
    """z-depth of a fixed mesh at any camera (both sides of every face; OpenGL when there, else the
    reference z-buffer); 0 where uncovered."""

    def __init__(self, mesh: trimesh.Trimesh):
        from omnirecon.render.raster import MeshRasterizer, gl_available

        self.mesh = mesh
        self.rast = MeshRasterizer.from_trimesh(mesh, cull_back_faces=False) if len(mesh.faces) and gl_available() \
            else None

    def __call__(self, camera: Cameras) -> np.ndarray:
        """``# [H, W]`` float32"""
        if len(self.mesh.faces) == 0:
            return np.zeros((camera.height, camera.width), np.float32)
        if self.rast is not None:  # the depth pass (the G-buffer's depth to float rounding, 0 where no face)
            return self.rast.depth(camera).numpy().copy()
        from omnirecon.mesh.geometry import mesh_depth

        return mesh_depth(self.mesh, camera).astype(np.float32)

    def close(self) -> None:
        if self.rast is not None:
            self.rast.close()


def render_depth(mesh: trimesh.Trimesh, camera: Cameras) -> np.ndarray:
    """z-depth of ``mesh`` at ``camera``'s pixel centres, 0 where uncovered. ``# [H, W]`` float32"""
    r = DepthRenderer(mesh)
    try:
        return r(camera)
    finally:
        r.close()


def nearest_fill(depth: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``depth`` with every pixel outside ``known`` set to its nearest known pixel's value (0 when
    nothing is known). ``# [H, W]``"""
    from scipy.ndimage import distance_transform_edt

    if not known.any():
        return np.zeros_like(depth)
    _, (rows, cols) = distance_transform_edt(~known, return_indices=True)
    return depth[rows, cols]


def pixel_grid_surface(camera: Cameras, depth: np.ndarray, region: np.ndarray, edge: float = 0.03) -> trimesh.Trimesh:
    """Two triangles per pixel of ``region # [H, W]`` at ``depth # [H, W]`` (> 0 on the region).

    Each pixel gets four corners on the rays of the image points ``(c + 0.25, r)``,
    ``(c + 1.25, r)``, ``(c + 0.25, r + 1)``, ``(c + 1.25, r + 1)``, so its centre ``(c + 0.5, r + 0.5)``
    falls strictly inside the triangle ``(top-left, bottom-left, bottom-right)`` whatever the depths.
    A corner's depth is the mean over the region pixels around it whose depth is within ``edge``
    (relative) of the pixel's own: smooth surfaces join up, and no sheet is stretched across a depth
    edge (a foreground pixel beside the background keeps its own depth). Where neighbouring pixels' corners
    agree (bit for bit), they are one vertex (:func:`omnirecon.mesh.clean.weld`; every face kept, in pixel order):
    a smooth region is one connected sheet, as written files and quadric decimation expect."""
    H, W = region.shape
    d = np.where(region, depth, 0.0).astype(np.float64)
    pad = np.pad(d, 1)  # pixel (r, c) at pad[r + 1, c + 1]
    pr, pc = np.nonzero(region)
    own = d[pr, pc]  # [P]
    corners = []
    for dr, dc in ((0, 0), (0, 1), (1, 0), (1, 1)):  # top-left, top-right, bottom-left, bottom-right corner
        # the four pixels around corner (pr + dr, pc + dc): rows pr + dr - 1 .. pr + dr, cols pc + dc - 1 .. pc + dc
        near = np.stack([pad[pr + dr + a, pc + dc + b] for a in (0, 1) for b in (0, 1)])  # [4, P]
        ok = (near > 0) & (np.abs(near - own) <= edge * own)
        corners.append((near * ok).sum(0) / np.maximum(ok.sum(0), 1))  # own pixel is always ok
    cd = np.stack(corners, 1)  # [P, 4]
    u = np.stack([pc + 0.25, pc + 1.25, pc + 0.25, pc + 1.25], 1)
    v = np.stack([pr, pr, pr + 1, pr + 1], 1).astype(np.float64)
    uv = torch.from_numpy(np.stack([u, v], -1).reshape(1, -1, 2))
    cam = camera.to(dtype=torch.float64)
    verts = cam.unproject(uv, torch.from_numpy(cd.reshape(1, -1)))[0].numpy()  # [4P, 3]
    base = 4 * np.arange(len(pr))
    a, b, c, e = base, base + 1, base + 2, base + 3  # top-left, top-right, bottom-left, bottom-right
    # OpenCV camera (x right, y down): (a, c, e) and (a, e, b) wind counter-clockwise seen from the camera
    faces = np.concatenate([np.stack([a, c, e], 1), np.stack([a, e, b], 1)])
    verts, welded = weld(verts, faces)  # a pixel's four corners lie on four distinct rays: no face collapses
    return trimesh.Trimesh(verts, welded, process=False)


def occluding(camera: Cameras, depth: np.ndarray, region: np.ndarray, others: Cameras, others_depth: np.ndarray,
              rel: float) -> np.ndarray:
    """Pixels of ``region # [H, W]`` whose point at ``depth # [H, W]`` (pixel centres) lies in front of the
    surface some other view sees: it projects into one of ``others`` (``M`` cameras, z-depth of the mesh at
    them ``others_depth # [M, H, W]``, 0 = none) at a z-depth more than ``rel`` (relative) nearer than the
    mesh there (the nearest of the four pixels around the projection, so a depth edge flags nothing). That view
    sees through the point, so a fill there would hide surface it saw (on fern, such
    fills from the views' own unconfirmed stereo depth covered part of the held-out pixels and doubled their
    error). ``# [H, W]`` bool"""
    out = np.zeros(region.shape, dtype=bool)
    rows, cols = np.nonzero(region & (depth > 0))
    if not len(rows) or not len(others):
        return out
    cam = camera.to(dtype=torch.float64)
    uv = torch.from_numpy(np.stack([cols + 0.5, rows + 0.5], -1)[None].astype(np.float64))  # [1, P, 2]
    X = cam.unproject(uv, torch.from_numpy(depth[rows, cols].astype(np.float64))[None])[0]  # [P, 3]
    hit = np.zeros(len(rows), dtype=bool)
    for j in range(len(others)):
        pj = others[j].to(dtype=torch.float64).project(X)
        inside = pj.in_image[0].numpy()
        x0 = np.floor(pj.uv[0, :, 0].numpy() - 0.5).astype(np.int64)
        y0 = np.floor(pj.uv[0, :, 1].numpy() - 0.5).astype(np.int64)
        near = np.stack([others_depth[j][np.clip(y0 + a, 0, others.height - 1), np.clip(x0 + b, 0, others.width - 1)]
                         for a in (0, 1) for b in (0, 1)])  # [4, P] the pixels around the projection
        seen = np.where(near > 0, near, np.inf).min(0)  # the nearest of them: no flags from depth edges
        hit |= inside & np.isfinite(seen) & (pj.depth[0].numpy() < (1.0 - rel) * seen)
    out[rows[hit], cols[hit]] = True
    return out


def padded_camera(camera: Cameras, pad: int) -> Cameras:
    """``camera`` (one) with its image grown by ``pad`` pixels on every side (same rays for the old pixels)."""
    return Cameras(camera.fx, camera.fy, camera.cx + pad, camera.cy + pad, camera.c2w, camera.width + 2 * pad,
                   camera.height + 2 * pad)


def backdrop_sheet(cameras: Cameras, bounds: Tensor, pad: float, cell: int = 16) -> trimesh.Trimesh:
    """The backdrop layer of a forward-facing scene as a surface: for each view, its image grown by ``pad``
    (a fraction of the long side) on every side, in cells of ``cell`` pixels, on the bounds box's far side
    (where each cell's ray leaves the box). Behind every other surface, it is what a ray sees that misses
    them all: gaps between surfaces seen from between the views, and past the views' borders (on fern, a few
    held-out pixels in a hundred after the per-pixel fills). About ``2 (W / cell) (H / cell)`` faces a view."""
    from omnirecon.mesh.fusion import exit_depth

    grow = round(pad * max(cameras.width, cameras.height))
    sheets = []
    for i in range(len(cameras)):
        c = padded_camera(cameras[i], grow)
        coarse = Cameras(c.fx / cell, c.fy / cell, c.cx / cell, c.cy / cell, c.c2w, -(-c.width // cell),
                         -(-c.height // cell))
        d = exit_depth(coarse, bounds)[0].numpy()
        if (d > 0).any():
            sheets.append(pixel_grid_surface(coarse, d, d > 0, edge=np.inf))  # the exit depth is continuous: one sheet
    return trimesh.util.concatenate(sheets) if sheets else trimesh.Trimesh()


def content_region(view_depth: Tensor | None, mask: np.ndarray | None, forward: bool, shape) -> np.ndarray:
    """Pixels of a view that should be covered (module docstring). ``# [H, W]`` bool"""
    if mask is not None:
        return mask.astype(bool)
    if forward or view_depth is None:
        return np.ones(shape, dtype=bool)
    from scipy.ndimage import binary_closing, binary_fill_holes

    has = view_depth.numpy() > 0
    return binary_fill_holes(binary_closing(has, np.ones((5, 5), dtype=bool), border_value=1))


def complete_surface(mesh: trimesh.Trimesh, cameras: Cameras, depths: Tensor | None, bounds: Tensor,
                     masks: np.ndarray | None = None, forward: bool = False,
                     occlusion_rel: float | None = None, backdrop_pad: float = -1.0,
                     content: np.ndarray | None = None) -> tuple[trimesh.Trimesh, dict]:
    """``mesh`` plus a fill surface covering every content pixel of every view (module docstring).

    Args:
        cameras: The ``N`` training views.
        depths: The depth source's map at each of them (0 = none), or ``None``. ``# [N, H, W]``
        bounds: ``[min, max]`` of the scene; the backdrop is its far side. ``# [2, 3]``
        masks: Content pixels (dilated object masks) of each view. ``# [N, H, W]`` bool
        forward: A forward-facing or unbounded scene: cover every pixel, clamp far depth onto the backdrop.
        occlusion_rel: When given, a fill point in front of the surface another view sees (:func:`occluding`,
            this relative depth margin) goes to the backdrop (forward-facing scenes) or is left out.
        backdrop_pad: Forward-facing scenes, when ``>= 0``: add the backdrop layer (:func:`backdrop_sheet`) over
            each view's image grown by this fraction of the long side.
        content: Pixels to cover besides the region found from ``masks`` or the depth maps (e.g. every pixel
            whose colour is not the scene's known background). ``# [N, H, W]`` bool

    Returns:
        The completed mesh and a record (fill faces, pixels filled per source of depth, coverage of
        the content pixels before and after).
    """
    from omnirecon.mesh.fusion import exit_depth

    fills: list[trimesh.Trimesh] = []
    stats = {"from_depth_map": 0, "backdrop": 0, "hole_filled": 0, "content_pixels": 0, "covered_before": 0,
             "occluding": 0}
    base = DepthRenderer(mesh)  # the fused mesh is drawn once per view; the (small) fills so far beside it
    seen = None if occlusion_rel is None else np.stack([base(cameras[j]) for j in range(len(cameras))])  # [N, H, W]
    for i in range(len(cameras)):
        cam = cameras[i]
        shape = (cam.height, cam.width)
        view_depth = None if depths is None else depths[i].float()
        region = content_region(view_depth, None if masks is None else masks[i], forward, shape)
        if content is not None:
            region = region | content[i]
        mesh_d = base(cam)
        if fills:
            fill_d = render_depth(trimesh.util.concatenate(fills), cam)
            mesh_d = np.where((fill_d > 0) & ((mesh_d <= 0) | (fill_d < mesh_d)), fill_d, mesh_d)
        covered = mesh_d > 0
        stats["content_pixels"] += int(region.sum())
        stats["covered_before"] += int((region & covered).sum())
        todo = region & ~covered
        if not todo.any():
            continue
        mapped = np.zeros(shape, np.float32) if view_depth is None else view_depth.numpy()
        backdrop = exit_depth(cam, bounds)[0].numpy() if forward else None
        d = np.where(covered, mesh_d, 0.0)
        use_map = todo & (mapped > 0)
        d = np.where(use_map, mapped, d)
        if backdrop is not None:  # far content onto the backdrop; no depth at all: the backdrop
            far = todo & (backdrop > 0) & ((d <= 0) | (d > backdrop))
            stats["backdrop"] += int((far & ~use_map).sum())
            d = np.where(far & ((d <= 0) | (d > backdrop)), backdrop, d)
        stats["from_depth_map"] += int(use_map.sum())
        known = d > 0
        holes = todo & ~known
        stats["hole_filled"] += int(holes.sum())
        d = np.where(holes, nearest_fill(d, known), d)
        if backdrop is not None:
            d = np.where(todo & (backdrop > 0), np.minimum(d, backdrop), d)
        ok = todo & (d > 0)
        if seen is not None and len(cameras) > 1:
            others = [j for j in range(len(cameras)) if j != i]
            bad = occluding(cam, d, ok, cameras[others], seen[others], occlusion_rel)
            stats["occluding"] += int(bad.sum())
            if backdrop is not None:
                d = np.where(bad & (backdrop > 0), backdrop, d)
                bad &= ~(backdrop > 0)
            ok &= ~bad
        if not ok.any():
            continue
        fills.append(pixel_grid_surface(cam, d, ok))
    base.close()
    current = trimesh.util.concatenate([mesh, *fills]) if fills and len(mesh.faces) else (
        trimesh.util.concatenate(fills) if fills else mesh)
    if forward and backdrop_pad >= 0:
        sheet = backdrop_sheet(cameras, bounds, backdrop_pad)
        stats["backdrop_faces"] = len(sheet.faces)
        if len(sheet.faces):
            fills.append(sheet)
            current = trimesh.util.concatenate([current, sheet]) if len(current.faces) else sheet
    info = {**stats, "fill_faces": int(sum(len(f.faces) for f in fills)),
            "coverage_before": stats["covered_before"] / max(1, stats["content_pixels"])}
    return current, info
