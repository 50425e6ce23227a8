"""Depth maps -> a truncated signed distance grid -> a surface: the fusion stage of the mesh pipeline.

One projective TSDF (:func:`integrate`, the only one in the package) with the switches the presets
set (:class:`omnirecon.mesh.build.MeshOptions`):

* **Scale from the depth maps** (:func:`auto_scale`): the voxel is half the pixel footprint at the
  median depth (with exact depth at every view of a 128-px procedural scene, a one-footprint voxel
  lost mesh-path PSNR at object outlines, half a footprint much less), and the truncation,
  4 voxels, widens to twice the depth error the maps show (:func:`depth_disagreement`).
* **Sub-pixel depth** (:func:`sample_depth`): each voxel reads the depth map bilinearly at its exact
  projection, falling back to the nearest pixel across depth edges (VolRecon's protocol: nearest).
* **Confidence weights per pixel**: the depth source's own confidence times a forward-backward
  reprojection check between maps (:func:`consistency`, MVS fusion's geometric test), so a
  corrupted map loses its vote where the others disagree.
* **Free-space carving**: pixels with a confident "no surface" (outside the object masks) mark the
  voxels they see through as empty.
* **Only near surfaces** (:func:`surface_band`): the grid is split into blocks of 4^3 voxels and only
  the blocks within the truncation of some depth sample are integrated, so
  the cost follows the surface area, not the volume of the bounds.
* **Visibility violations** (:func:`occlusion_votes`): depth behind a surface other maps see is too far;
  (:func:`free_space_votes`) depth in front of a surface other maps see past is too near.

Size: the TSDF and the checks between depth maps that set its weights share the projection helpers.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import trimesh
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError

BLOCK = 4
"""Voxels per block side for :func:`surface_band`."""


# ---------------------------------------------------------------------- the grid
class TSDFVolume:
    """A truncated signed distance grid; voxel ``(i, j, k)`` sits at ``origin + voxel * (i, j, k)``.

    ``tsdf``: signed distance over the truncation in [-1, 1], positive in front of surfaces, 1 where
    unobserved (``# [X, Y, Z]`` float32); ``weight``: summed observation weight, 0 = unobserved
    (``# [X, Y, Z]`` float32); ``origin # [3]`` float64; ``voxel`` and ``trunc`` in scene units."""

    def __init__(self, tsdf: Tensor, weight: Tensor, origin: Tensor, voxel: float, trunc: float):
        self.tsdf, self.weight, self.origin, self.voxel, self.trunc = tsdf, weight, origin, voxel, trunc

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.tsdf.shape)

    def positions(self, flat: Tensor) -> Tensor:
        """Centres of voxels with flat (C-order) indices ``flat # [P]``. ``# [P, 3]``"""
        X, Y, Z = self.shape
        ijk = torch.stack([flat // (Y * Z), (flat // Z) % Y, flat % Z], -1)
        return self.origin.to(self.tsdf.device) + self.voxel * ijk.to(torch.float64)


GRID_BYTES = 12
"""Bytes per voxel of the TSDF grid while a mesh is made: the distance and weight grids (float32 each) and a
margin for the masks and copies marching cubes and the observed-voxel test make (inside the band)."""


def grid_shape(bounds: Tensor, voxel: float, trunc: float) -> tuple[Tensor, tuple[int, int, int]]:
    """``(lower corner # [3], voxels per axis)`` of the grid over ``bounds # [2, 3]`` padded by ``trunc`` plus 2 voxels."""
    pad = trunc + 2 * voxel
    lo = bounds[0].double() - pad
    hi = bounds[1].double() + pad
    dims = torch.ceil((hi - lo) / voxel).long() + 1
    return lo, tuple(int(d) for d in dims)


def check_grid_memory(bounds: Tensor, voxel: float, trunc: float, fraction: float) -> None:
    """Refuse (naming ``--voxel``, given as ``fraction`` of the bounds diagonal) a grid the memory cannot hold."""
    from omnirecon.preflight import check_memory

    need = math.prod(grid_shape(bounds, voxel, trunc)[1]) * GRID_BYTES
    check_memory(need, "--voxel", lambda share: f"{fraction / share ** (1 / 3) * 1.05:.2g}")


def empty_volume(bounds: Tensor, voxel: float, trunc: float, device="cpu") -> TSDFVolume:
    """An unobserved grid over ``bounds # [2, 3]`` padded by ``trunc`` plus 2 voxels on every side, so
    that surfaces on the bounds (a ground plane) get voxels on both sides."""
    lo, shape = grid_shape(bounds, voxel, trunc)
    if math.prod(shape) > 1 << 40:  # far past any memory (check_grid_memory names --voxel before this)
        raise InputError(f"the TSDF grid would have {math.prod(shape):,} voxels", None, "use a larger --voxel")
    return TSDFVolume(torch.ones(shape, device=device), torch.zeros(shape, device=device), lo, voxel, trunc)


def surface_band(volume: TSDFVolume, cameras: Cameras, depths: Tensor) -> Tensor:
    """Flat indices of the voxels of every block (:data:`BLOCK`^3 voxels) that holds a depth sample
    moved along its ray by up to the truncation: the only voxels a zero crossing can lie in. Pixels
    are sampled at most one block apart on the surface, and along each ray at steps of half the
    truncation (at most one block), so the marked blocks join up. ``# [P]`` int32, increasing"""
    X, Y, Z = volume.shape
    nb = np.array([-(-X // BLOCK), -(-Y // BLOCK), -(-Z // BLOCK)])
    marked = np.zeros(tuple(nb), dtype=bool)
    cams = cameras.to(dtype=torch.float64)
    footprint = pixel_footprint(cams, depths)
    step = max(1, int(BLOCK * volume.voxel / (2 * footprint)))
    o, d = cams.image_rays(normalize=False)  # [N, H, W, 3]
    o, d, z = o[:, ::step, ::step], d[:, ::step, ::step], depths.double()[:, ::step, ::step]
    has = z > 0
    o, d, z = o[has].float(), d[has].float(), z[has].float()
    origin = volume.origin.float()
    n_along = int(np.ceil(2 * volume.trunc / min(volume.trunc / 2, BLOCK * volume.voxel)))
    for dz in np.linspace(-volume.trunc, volume.trunc, n_along + 1):
        p = o + d * (z + float(dz))[:, None]
        b = torch.floor((p - origin) / (volume.voxel * BLOCK)).long().numpy()
        b = b[((b >= 0) & (b < nb)).all(1)]
        marked[b[:, 0], b[:, 1], b[:, 2]] = True
    return block_voxels(marked, volume.shape)


def block_voxels(marked: np.ndarray, shape: tuple[int, int, int]) -> Tensor:
    """Flat (C-order) indices of the voxels of the marked blocks (``marked # [BX, BY, BZ]`` bool, :data:`BLOCK`^3
    voxels each) of a grid of ``shape``, increasing, int32 (a grid has at most 2^30 voxels: :func:`empty_volume`).
    Built from each block's first voxel plus the offsets inside a block (4 bytes per voxel, at most 8 while
    building): ethiopianHead's band of a 385x372x501 grid took 3 GB as ``[V, 3]`` int64 coordinates. ``# [P]``"""
    X, Y, Z = shape
    off = np.stack(np.meshgrid(*[np.arange(BLOCK)] * 3, indexing="ij"), -1).reshape(-1, 3)  # [BLOCK^3, 3]
    inner = (off[:, 0] * Y + off[:, 1]) * Z + off[:, 2]  # [BLOCK^3]
    parts = []
    for bx in range(marked.shape[0]):  # one slab of blocks at a time: increasing flat indices, slab by slab
        by, bz = np.nonzero(marked[bx])
        if len(by) == 0:
            continue
        first = ((bx * BLOCK * Y + by * BLOCK) * Z + bz * BLOCK).astype(np.int64)  # [B]
        flat = (first[:, None] + inner[None]).reshape(-1)  # [B * BLOCK^3]
        edge = (bx * BLOCK + BLOCK > X) | (by * BLOCK + BLOCK > Y) | (bz * BLOCK + BLOCK > Z)  # blocks past the grid
        if edge.any():
            ijk = np.stack([np.full(len(by), bx), by, bz], -1)[:, None] * BLOCK + off[None]  # [B, BLOCK^3, 3]
            flat = flat[(ijk < np.array([X, Y, Z])).all(-1).reshape(-1)]
        flat.sort()
        parts.append(flat.astype(np.int32))
    return torch.from_numpy(np.concatenate(parts) if parts else np.zeros(0, np.int32))


# ---------------------------------------------------------------------- integration
def sample_depth(depth: Tensor, u: Tensor, v: Tensor, edge: float, pix: Tensor | None = None) -> Tensor:
    """Depth of ``depth # [H, W]`` (0 = none) at pixel coordinates ``u, v # [P]`` (pixel centres at
    +0.5): bilinear where the four surrounding pixels all have depth within ``edge`` of each other,
    else the nearest pixel's. Points outside the image read 0. ``pix # [P]``: the points all lie in the image and
    these are their flat pixel indices (``v.long() * W + u.long()``; the same reads, fewer steps). ``# [P]``"""
    H, W = depth.shape
    flat = depth.reshape(-1)
    if pix is None:
        col = torch.floor(u).long()
        row = torch.floor(v).long()
        inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
        nearest = torch.where(inside, flat.index_select(0, row.clamp(0, H - 1) * W + col.clamp(0, W - 1)),
                              torch.zeros_like(u))
    else:  # in the image: floor is truncation, the clamps do nothing, every point is inside
        inside, nearest = None, flat.index_select(0, pix)
    x, y = u - 0.5, v - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = x - x0, y - y0
    x0, y0 = x0.long(), y0.long()
    x1, y1 = x0 + 1, y0 + 1
    cx0, cx1, cy0, cy1 = x0.clamp(0, W - 1), x1.clamp(0, W - 1), y0.clamp(0, H - 1), y1.clamp(0, H - 1)
    r0, r1 = cy0 * W, cy1 * W
    d00, d01 = flat.index_select(0, r0 + cx0), flat.index_select(0, r0 + cx1)
    d10, d11 = flat.index_select(0, r1 + cx0), flat.index_select(0, r1 + cx1)
    lo = torch.minimum(torch.minimum(d00, d01), torch.minimum(d10, d11))  # [P] (min and max are exact: the
    hi = torch.maximum(torch.maximum(d00, d01), torch.maximum(d10, d11))  # same test as over a stacked [4, P])
    ok = (lo > 0) & (hi - lo <= edge)
    bil = (d00 * (1 - fx) + d01 * fx) * (1 - fy) + (d10 * (1 - fx) + d11 * fx) * fy
    return torch.where(ok if inside is None else ok & inside, bil, nearest)


def integrate(volume: TSDFVolume, cameras: Cameras, depths: Tensor, weights: Tensor | None = None,
              free: Tensor | None = None, chunk: int = 1 << 20, bilinear: bool = True,
              voxels: Tensor | None = None) -> None:
    """Fuse z-depth maps into ``volume`` in place (weighted projective TSDF), one after another.

    A voxel at depth ``z`` in front of a camera that projects onto a pixel with depth ``d > 0``
    gets the observation ``min(1, (d - z) / trunc)`` with that pixel's weight, unless it lies more
    than ``trunc`` behind the surface; a voxel projecting onto a ``free`` pixel (no surface on its
    ray, e.g. outside the object mask) gets ``+1`` with the pixel's weight. Observations are
    averaged by weight, in the order of the maps.

    The voxels are visited in chunks, each chunk projected into every map in turn: the same updates in the
    same order per voxel as integrating the maps one by one (bit for bit: ``tests/mesh/test_fusion.py``), with
    each chunk's positions computed and its TSDF read and written once instead of once per map.

    Args:
        cameras: ``N`` cameras (OpenCV, camera-to-world).
        depths: z-depth per pixel, 0 = none. ``# [N, H, W]`` (or ``# [H, W]`` with one camera)
        weights: Confidence of each pixel (default 1 where there is depth). ``# [N, H, W]``
        free: Pixels whose ray is empty as far as the grid goes. ``# [N, H, W]`` bool
        bilinear: Read depth bilinearly (:func:`sample_depth`) instead of at the nearest pixel.
        voxels: Flat indices of the voxels to update (:func:`surface_band`; default every voxel).
    """
    dev = volume.tsdf.device
    if depths.dim() == 2:  # one map
        depths = depths[None]
        weights = None if weights is None else weights[None]
        free = None if free is None else free[None]
    maps = [_map_for_integration(volume, cameras[i], depths[i], None if weights is None else weights[i],
                                 None if free is None else free[i]) for i in range(len(depths))]
    _, Y, Z = volume.shape
    YZ = Y * Z
    tsdf, wsum = volume.tsdf.view(-1), volume.weight.view(-1)
    total = tsdf.numel() if voxels is None else len(voxels)
    for start in range(0, total, chunk):
        stop = min(start + chunk, total)
        flat = torch.arange(start, stop, device=dev) if voxels is None else voxels[start:stop].to(dev, torch.int64)
        # voxel centres relative to the grid origin (float32 is exact enough), one [P] tensor per axis
        grid = [volume.voxel * (flat // YZ).float(), volume.voxel * ((flat // Z) % Y).float(), volume.voxel * (flat % Z).float()]
        ts, ws = tsdf.index_select(0, flat), wsum.index_select(0, flat)  # [P] this chunk's TSDF and weight
        for m in maps:
            _integrate_chunk(volume.trunc, grid, ts, ws, m, bilinear)
        tsdf[flat], wsum[flat] = ts, ws


def _map_for_integration(volume: TSDFVolume, camera: Cameras, depth: Tensor, weight: Tensor | None,
                         free: Tensor | None) -> dict:
    """One map's pixels (flat) and projection for :func:`_integrate_chunk`."""
    dev = volume.tsdf.device
    depth = depth.to(dev, torch.float32)
    wmap = (depth > 0).float() if weight is None else weight.to(dev, torch.float32) * (depth > 0)
    if free is not None:
        free = free.to(dev) & (depth <= 0)
        fw = torch.where(free, torch.ones_like(depth) if weight is None else weight.to(dev, torch.float32), 0.0)
        wmap = wmap + fw
    w2c = camera.w2c[0].to(dev, torch.float64)
    R, t = w2c[:3, :3], w2c[:3, 3]
    return {"depth": depth, "wflat": wmap.reshape(-1), "dflat": depth.reshape(-1),
            "freeflat": None if free is None else free.reshape(-1),
            "R": R.float(), "t": (R @ volume.origin.to(dev) + t).float(),
            "f": tuple(float(getattr(camera, k)[0]) for k in ("fx", "fy", "cx", "cy"))}


def _integrate_chunk(trunc: float, grid: list[Tensor], ts: Tensor, ws: Tensor, m: dict, bilinear: bool) -> None:
    """One map (:func:`_map_for_integration`) into a chunk of voxels at ``grid`` (x, y, z ``# [P]`` each, relative to
    the grid origin) whose TSDF and weight are ``ts, ws # [P]`` (updated in place)."""
    H, W = m["depth"].shape
    fx, fy, cx, cy = m["f"]
    R, t = m["R"], m["t"]
    x, y, z = grid
    # camera frame, p = grid @ R.T + t written out: the same float32 products and sums in the same order as that
    # product (equal bit for bit on the CPU's BLAS: tests/mesh/test_fusion.py), at half its cost for 3x3
    px = x * R[0, 0] + y * R[0, 1] + z * R[0, 2] + t[0]  # [P]
    py = x * R[1, 0] + y * R[1, 1] + z * R[1, 2] + t[1]
    z = x * R[2, 0] + y * R[2, 1] + z * R[2, 2] + t[2]
    zs = z.clamp_min(1e-9)
    u = fx * px / zs + cx
    v = fy * py / zs + cy
    inside = (z > 1e-9) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    at = inside.nonzero()[:, 0]  # [Q] the chunk's voxels in the image
    z, u, v = z.index_select(0, at), u.index_select(0, at), v.index_select(0, at)
    pix = v.long() * W + u.long()
    w = m["wflat"].index_select(0, pix)
    keep = (w > 0).nonzero()[:, 0]
    at, z, u, v, pix, w = (x.index_select(0, keep) for x in (at, z, u, v, pix, w))
    d = sample_depth(m["depth"], u, v, trunc, pix) if bilinear else m["dflat"].index_select(0, pix)
    sdf = d - z
    obs = (sdf / trunc).clamp(max=1.0)
    use = (d > 0) & (sdf >= -trunc)
    if m["freeflat"] is not None:
        is_free = m["freeflat"].index_select(0, pix)
        obs = torch.where(is_free, torch.ones_like(obs), obs)
        use = use | is_free
    sel = use.nonzero()[:, 0]
    at, obs, w = at.index_select(0, sel), obs.index_select(0, sel), w.index_select(0, sel)
    w_old = ws.index_select(0, at)
    ts[at] = (ts.index_select(0, at) * w_old + obs * w) / (w_old + w)
    ws[at] = w_old + w


def fuse(cameras: Cameras, depths: Tensor, bounds: Tensor, voxel: float, trunc: float, weights: Tensor | None = None,
         free: Tensor | None = None, chunk: int = 1 << 20, bilinear: bool = True, device="cpu",
         on_view=None, band: bool = True) -> TSDFVolume:
    """Weighted TSDF of ``N`` z-depth maps over ``bounds`` (:func:`integrate`).

    Args:
        depths: z-depth maps, 0 = none. ``# [N, H, W]``
        weights: Per-pixel confidence (default 1). ``# [N, H, W]``
        free: Pixels whose ray is empty (carved). ``# [N, H, W]`` bool
        band: Integrate only the blocks near some depth sample (:func:`surface_band`): the same
            surface, at a cost that follows the surface area.
        on_view: Called with no argument once per view when the maps are fused (progress bars).
    """
    if depths.shape[0] != len(cameras) or (weights is not None and weights.shape != depths.shape):
        raise ValueError(f"{len(cameras)} cameras, depths {tuple(depths.shape)}")
    volume = empty_volume(bounds, voxel, trunc, device)
    voxels = surface_band(volume, cameras, depths) if band and (depths > 0).any() else None
    integrate(volume, cameras, depths, weights, free, chunk, bilinear, voxels)
    for _ in range(len(cameras) if on_view is not None else 0):
        on_view()
    return volume


def extract_mesh(volume: TSDFVolume, level: float = 0.0) -> trimesh.Trimesh:
    """Marching cubes (scikit-image, Lewiner) of ``volume`` at ``level``, in scene coordinates.

    Only surface between observed voxels is kept: a face survives when each of its vertices lies
    on a grid edge whose two voxels were both observed, so no surface appears where observed space
    meets unobserved space (behind the truncation band). Faces wind counter-clockwise seen from the
    free side, so normals point towards the cameras. Returns an empty mesh when nothing crosses
    the level.
    """
    from skimage.measure import marching_cubes

    tsdf = volume.tsdf.cpu().numpy()
    seen = volume.weight.cpu().numpy() > 0
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), process=False)
    if not seen.any() or not (tsdf[seen].min() < level < tsdf.max()):
        return empty
    verts, faces, _, _ = marching_cubes(tsdf, level, allow_degenerate=False, mask=seen)  # verts in voxel units
    if len(faces) == 0:
        return empty
    lo = np.floor(verts).astype(np.int64)
    hi = np.minimum(np.ceil(verts).astype(np.int64), np.array(tsdf.shape) - 1)
    ok = seen[lo[:, 0], lo[:, 1], lo[:, 2]] & seen[hi[:, 0], hi[:, 1], hi[:, 2]]  # [V]
    faces = faces[ok[faces].all(1)]
    if len(faces) == 0:
        return empty
    mesh = trimesh.Trimesh(verts.astype(np.float64) * volume.voxel + volume.origin.numpy(), faces.astype(np.int64),
                           process=False)
    mesh.remove_unreferenced_vertices()
    return mesh


# ---------------------------------------------------------------------- scale
def pixel_footprint(cameras: Cameras, depths: Tensor) -> float:
    """Median size of one pixel on the surface (``z / f``) over every pixel with depth (scene units)."""
    f = 0.5 * (cameras.fx + cameras.fy).double()  # [N]
    d = depths.double()
    fp = d / f[:, None, None]
    fp = fp[d > 0]
    if fp.numel() == 0:
        raise InputError("no depth map has a valid pixel", None, "check the depth source (or --min-acc)")
    return float(fp.median())


def auto_scale(cameras: Cameras, depths: Tensor, voxel_px: float = 0.5, trunc_voxels: float = 4.0,
               depth_error: float = 0.0) -> tuple[float, float]:
    """Voxel edge and truncation (scene units) from the depth maps: the voxel is ``voxel_px`` pixel
    footprints at the median depth; the truncation is ``trunc_voxels`` voxels or, if larger, twice the
    expected depth error (``depth_error`` relative times the median depth)."""
    voxel = voxel_px * pixel_footprint(cameras, depths)
    d = depths[depths > 0].double()
    trunc = max(trunc_voxels * voxel, 2.0 * depth_error * float(d.median()))
    return voxel, trunc


# ---------------------------------------------------------------------- confidence between maps
def _pixels(H: int, W: int) -> Tensor:
    vv, uu = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                            indexing="ij")
    return torch.stack([uu, vv], -1).reshape(-1, 2)  # [HW, 2]


def _near_maps(cams: Cameras, k: int) -> list[list[int]]:
    from omnirecon.cameras import nearest_views

    n = len(cams)
    if n - 1 <= k:
        return [[j for j in range(n) if j != i] for i in range(n)]
    return nearest_views(cams, cams, k, exclude=torch.arange(n)).tolist()


def _map_points(cams: Cameras, d: Tensor, pix: Tensor, max_pairs: int):
    """For each map ``i`` with depth: ``(i, its nearest maps, flat indices of its pixels with depth # [P],
    those pixels unprojected to world points # [P, 3])``; ``d # [N, H, W]`` float64, ``pix`` from :func:`_pixels`."""
    for i, near in enumerate(_near_maps(cams, max_pairs)):
        di = d[i].reshape(-1)
        has = di > 0
        if not has.any():
            continue
        yield i, near, torch.nonzero(has)[:, 0], cams[i].unproject(pix[has][None], di[has][None])[0]


def consistency(cameras: Cameras, depths: Tensor, rel: float = 0.01, px: float = 1.0, max_pairs: int = 8) -> Tensor:
    """Forward-backward reprojection agreement between depth maps (MVS fusion's geometric check).

    For each pixel ``p`` of map ``i`` with depth, and each of the ``max_pairs`` maps nearest to ``i``
    (cost linear in the maps): unproject ``p`` to the point ``X``, read map ``j`` at ``X``'s
    projection ``q`` (:func:`sample_depth`), unproject ``q`` with that depth and project it back into
    ``i``. Map ``j`` agrees when the point comes back within ``px`` pixels of ``p`` and its depth in
    ``i`` is within ``rel`` (relative) of ``p``'s.

    Returns the number of maps that agree with each pixel. ``# [N, H, W]`` float32
    """
    cams = cameras.to(dtype=torch.float64)
    N, H, W = depths.shape
    d = depths.double()
    pix = _pixels(H, W)
    agree = torch.zeros(N, H * W)
    for i, near, idx, Xi in _map_points(cams, d, pix, max_pairs):  # Xi: [P, 3] world
        for j in near:
            pj = cams[j].project(Xi)
            uvj = pj.uv[0]  # [P, 2]
            dj = sample_depth(d[j], uvj[:, 0], uvj[:, 1], rel * float(pj.depth[0].median()))
            ok = pj.in_image[0] & (dj > 0)
            back = cams[i].project(cams[j].unproject(uvj[None], dj[None])[0])
            err = (back.uv[0] - pix[idx]).norm(dim=-1)
            di = d[i].reshape(-1)[idx]  # [P]
            drel = (back.depth[0] - di).abs() / di
            agree[i, idx] += (ok & back.in_front[0] & (err <= px) & (drel <= rel)).float()
    return agree.reshape(N, H, W)


def occlusion_votes(cameras: Cameras, depths: Tensor, trusted: Tensor | None = None, rel: float = 0.05,
                    max_pairs: int = 8) -> Tensor:
    """How many other maps put a surface in front of each pixel's depth (a visibility violation).

    Every pixel of map ``j`` with depth (and ``trusted``, e.g. confirmed by a third map) is unprojected and
    projected into map ``i`` (z-buffer over the four pixel centres around each projection: the nearest point
    per pixel); map ``j`` votes against pixel ``p`` of
    ``i`` when that nearest point lies in front of ``p``'s depth by more than ``rel`` (relative). Real
    geometry cannot do that: ``i``'s ray would pass through a surface ``j`` sees, so ``i``'s depth is too far
    (a stereo mismatch onto the background behind an object) or ``j``'s point floats. Each map against its
    ``max_pairs`` nearest maps. ``# [N, H, W]`` float32
    """
    cams = cameras.to(dtype=torch.float64)
    N, H, W = depths.shape
    d = depths.double()
    pix = _pixels(H, W)
    ok = d > 0 if trusted is None else (d > 0) & trusted
    votes = torch.zeros(N, H * W)
    for i, near in enumerate(_near_maps(cams, max_pairs)):
        di = d[i].reshape(-1)
        if not (di > 0).any():
            continue
        for j in near:
            has = ok[j].reshape(-1)
            if not has.any():
                continue
            X = cams[j].unproject(pix[has][None], d[j].reshape(-1)[has][None])[0]  # [P, 3] world
            pi = cams[i].project(X)
            inside = pi.in_image[0]
            uv, z = pi.uv[0][inside], pi.depth[0][inside]
            front = torch.full((H * W,), float("inf"), dtype=torch.float64)
            c0, r0 = torch.floor(uv[:, 0] - 0.5).long(), torch.floor(uv[:, 1] - 0.5).long()
            for dr, dc in ((0, 0), (0, 1), (1, 0), (1, 1)):  # the 4 pixel centres around it: no gaps between points
                flat = (r0 + dr).clamp(0, H - 1) * W + (c0 + dc).clamp(0, W - 1)
                front.scatter_reduce_(0, flat, z, reduce="amin")
            votes[i] += ((di > 0) & (front < di * (1 - rel))).float()
    return votes.reshape(N, H, W)


def free_space_votes(cameras: Cameras, depths: Tensor, trusted: Tensor | None = None, rel: float = 0.03,
                     max_pairs: int = 8, reach: int = 2) -> Tensor:
    """How many other maps see past each pixel's point (a free-space violation, the mirror of
    :func:`occlusion_votes`).

    Each pixel of map ``i`` with depth is unprojected and projected into map ``j``; ``j`` votes against it when
    the ``2 reach x 2 reach`` pixels of ``j`` around the projection all hold (``trusted``) depth farther than the
    point by more than ``rel`` (relative; a wider ``reach`` spares points beside ``j``'s outlines): ``j``'s rays
    pass through the point, so it floats in space ``j`` saw empty (stereo giving the ground beside an object's
    base the object's depth). Each map against its ``max_pairs`` nearest maps. ``# [N, H, W]`` float32
    """
    cams = cameras.to(dtype=torch.float64)
    N, H, W = depths.shape
    d = depths.double()
    pix = _pixels(H, W)
    ok = d > 0 if trusted is None else (d > 0) & trusted
    around = [(a, b) for a in range(1 - reach, reach + 1) for b in range(1 - reach, reach + 1)]
    votes = torch.zeros(N, H * W)
    for i, near, idx, X in _map_points(cams, d, pix, max_pairs):  # X: [P, 3] world
        for j in near:
            pj = cams[j].project(X)
            uv, z = pj.uv[0], pj.depth[0]  # [P, 2], [P]
            c0, r0 = torch.floor(uv[:, 0] - 0.5).long(), torch.floor(uv[:, 1] - 0.5).long()
            inside = pj.in_image[0] & (c0 >= reach - 1) & (r0 >= reach - 1) & (c0 < W - reach) & (r0 < H - reach)
            dj = torch.where(ok[j], d[j], torch.zeros_like(d[j])).reshape(-1)  # untrusted: sees nothing past
            least = torch.full_like(z, float("inf"))
            for dr, dc in around:
                least = torch.minimum(least, dj[(r0 + dr).clamp(0, H - 1) * W + (c0 + dc).clamp(0, W - 1)])
            votes[i, idx] += (inside & (z > 0) & (least > z * (1 + rel))).float()
    return votes.reshape(N, H, W)


def geometric_weight(agree: Tensor, num_maps: int, need: int = 2, floor: float = 0.05) -> Tensor:
    """Weight from :func:`consistency` counts: ``min(1, agree / need)`` with ``need`` capped at the
    number of other maps, and at least ``floor`` (a pixel no other map can confirm still counts where
    nothing contradicts it). All ones for a single map."""
    need = min(need, num_maps - 1)
    if need < 1:
        return torch.ones_like(agree)
    return (agree / need).clamp(floor, 1.0)


def depth_disagreement(cameras: Cameras, depths: Tensor, max_rel: float = 0.1, max_pairs: int = 8,
                       step: int = 2) -> float | None:
    """The depth error the maps actually have, measured without ground truth: the median relative
    difference between a pixel's depth (every ``step``-th pixel) and the depth another map sees at its
    projection, over pairs that differ by less than ``max_rel`` (outliers and occlusions left out), each
    map against its ``max_pairs`` nearest maps. ``None`` with fewer than 2 maps or no overlap."""
    cams = cameras.to(dtype=torch.float64)
    N, H, W = depths.shape
    if N < 2:
        return None
    pix = _pixels(H, W).reshape(H, W, 2)[::step, ::step].reshape(-1, 2)
    diffs = []
    for i, near in enumerate(_near_maps(cams, max_pairs)):
        di = depths[i].double()[::step, ::step].reshape(-1)
        has = di > 0
        X = cams[i].unproject(pix[has][None], di[has][None])[0]
        for j in near:
            pj = cams[j].project(X)
            col = pj.uv[0, :, 0].floor().long().clamp(0, W - 1)
            row = pj.uv[0, :, 1].floor().long().clamp(0, H - 1)
            dj = depths[j].double()[row, col]
            ok = pj.in_image[0] & (dj > 0)
            rel = ((dj - pj.depth[0]).abs() / pj.depth[0])[ok]
            diffs.append(rel[rel < max_rel])
    allr = torch.cat(diffs) if diffs else torch.zeros(0)
    return float(allr.median()) if allr.numel() else None


def outside_bounds(cameras: Cameras, depths: Tensor, bounds: Tensor, margin: float) -> Tensor:
    """Pixels whose surface point lies outside ``bounds # [2, 3]`` grown by ``margin``. ``# [N, H, W]`` bool"""
    cams = cameras.to(dtype=torch.float64)
    lo, hi = bounds[0].double() - margin, bounds[1].double() + margin
    o, d = cams.image_rays(normalize=False)  # [N, H, W, 3]; t along d is the z-depth
    p = o + d * depths.double()[..., None]
    return ((p < lo) | (p > hi)).any(-1) & (depths > 0)


def exit_depth(cameras: Cameras, bounds: Tensor) -> Tensor:
    """z-depth at which each pixel's ray leaves the box ``bounds # [2, 3]`` (0 when it misses it): the
    backdrop a forward-facing scene's far content is clamped onto. ``# [N, H, W]``"""
    cams = cameras.to(dtype=torch.float64)
    o, d = cams.image_rays(normalize=False)
    lo, hi = bounds[0].double(), bounds[1].double()
    with torch.no_grad():
        inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
        t0, t1 = (lo - o) * inv, (hi - o) * inv
        t_near = torch.minimum(t0, t1).amax(-1)
        t_far = torch.maximum(t0, t1).amin(-1)
    return torch.where((t_far > t_near) & (t_far > 0), t_far, torch.zeros_like(t_far)).float()
