"""Meshes from rendered depth: the VolRecon / Omni-Recon protocol (``shared/docs/omnirecon.md`` §6).

A generalizable model has no global geometry to query on a grid (IBRNet's density and Omni-Recon's
SRDF depend on the ray), so the mesh is built from depth maps it renders:

1. **Depth at virtual views.** The model encodes the ``K`` source views once and renders a z-depth
   map at every source camera shifted along its own x axis (VolRecon shifts by 25 mm at a ~684 mm
   camera distance on DTU; here a shift is a fraction of the camera's distance to the centre of
   the scene bounds, default ``DTU_SHIFT``). A shift of 0 renders at the source view itself.
2. **TSDF fusion** (:func:`fuse_depths`): a projective truncated signed distance over a voxel grid
   covering the scene bounds (padded by the truncation), observation weight 1, view by view and in
   chunks of voxels, so memory is the grid plus one chunk.
3. **Marching cubes** (:func:`extract_mesh`, scikit-image) at level 0, only in cubes whose eight
   corners were observed, so no surface appears where observed space meets unobserved space.
4. **Cleaning** (:func:`clean_mesh`): keep vertices that project inside the (dilated) object mask of
   at least ``min_views`` source views (the reference's ``count > 1`` of 3), drop faces that no
   in-mask pixel ray of a source view hits first, and drop connected components smaller than a
   fraction of the largest.

All of it happens in the normalised scene frame; :func:`to_input_frame` maps the result back to the
user's coordinates (``Scene.to_input``) and :func:`export_mesh` writes PLY/OBJ/GLB.

Size: the mesh protocol end to end (depth at views, TSDF, marching cubes, cleaning, export) in the order
it runs.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError
from omnirecon.mesh.geometry import rasterize_mesh
from omnirecon.rays import Sources

DTU_SHIFT = 25.0 / 684.0
"""VolRecon's virtual-view shift (25 mm along the camera x axis) over DTU's camera distance to the
scene centre (684 mm on scan24, measured), as a fraction of the camera distance."""
DTU_DILATE = 11 / 800
"""The reference dilates masks with an 11-px ellipse at 800 px image width; as a fraction of the width."""
MESH_FORMATS = (".ply", ".obj", ".glb")
"""File types :func:`export_mesh` writes (chosen by the suffix)."""


@dataclass
class MeshOptions:
    """Every setting of the meshing protocol (recorded with each mesh)."""

    shifts: tuple[float, ...] = (DTU_SHIFT,)
    """Virtual views per source: x-axis shifts as fractions of the camera's distance to the bounds centre."""
    voxel: float | None = None
    """Voxel edge as a fraction of the bounds diagonal (1/256: ~3 mm on DTU, about one pixel at 128 px);
    ``None``: 1/256 with the reference fusion, the depth maps' pixel footprint with the fitted one."""
    trunc: float | None = None
    """TSDF truncation in voxels (the reference: 3); ``None``: 3, widened by the fitted fusion to twice
    the depth error the maps show."""
    fusion: str = "fit"
    """``"fit"`` (:mod:`omnirecon.mesh.fusion`: derived scale, confidence weights, sub-pixel depth,
    free-space carving with masks, face budget) or ``"reference"`` (VolRecon's protocol, this module)."""
    neighbours: int = 3
    """Sources per depth map when there are more views than this (each view from itself and its
    nearest views; cost linear in the views)."""
    weights: bool = True
    """Fitted fusion: weight pixels by forward-backward reprojection agreement between the maps."""
    max_faces: int = 200_000
    """Fitted fusion: decimate to at most this many faces (0 = no limit)."""
    depth_pass: str = "fine"
    """Which pass of a two-pass model (IBRNet, Omni-Recon) renders the depth maps: ``"fine"`` (coarse +
    importance samples, as the colour is rendered) or ``"coarse"`` (the coarse samples only, about 5x
    faster). Measured on the demo scene, all 18 views, omnirecon-tiny: fine F-score 0.665, Chamfer 0.50 %
    of the extent, held-out mesh depth abs rel 0.148; coarse 0.591, 0.55 %, 0.182."""
    min_acc: float = 0.5
    """Models that return ``acc`` (accumulated opacity): pixels below it have no depth, and depth is
    divided by ``acc`` (the expected depth of the ray given that it hits)."""
    min_views: int = 2
    """Keep vertices inside the masks of at least this many source views (when masks are given)."""
    dilate: float = DTU_DILATE
    """Mask dilation diameter as a fraction of the image width (0 = none)."""
    cull_hidden: bool = True
    """Drop faces that no (in-mask) pixel ray of a source view hits first."""
    min_component: float = 0.001
    """Drop connected components with fewer faces than this fraction of the largest (the reference drops
    components under 500 faces of meshes of ~10^5-10^6 faces). 1 % removed 63 % of the plane-sweep
    floor's fragmented DTU scan24 mesh (held-out IoU 0.48 -> 0.26); 0.1 % removes 17 % (IoU 0.44)."""
    chunk: int = 4096
    """Rays per rendering chunk."""
    voxel_chunk: int = 1 << 20
    """Voxels projected at once during fusion."""

    def check(self) -> None:
        if self.depth_pass not in ("coarse", "fine"):
            raise InputError(f"--depth-pass must be coarse or fine, got {self.depth_pass!r}", None, "use --depth-pass fine")
        if not self.shifts or not all(math.isfinite(s) and abs(s) < 1 for s in self.shifts):
            raise InputError(f"--shifts must be finite fractions in (-1, 1), got {list(self.shifts)}", None,
                             f"use e.g. --shifts {DTU_SHIFT:.4f}")
        if self.fusion not in ("fit", "reference"):
            raise InputError(f"--fusion must be fit or reference, got {self.fusion!r}", None, "use --fusion fit")
        if self.voxel is not None and not (math.isfinite(self.voxel) and 0 < self.voxel <= 0.1):
            raise InputError(f"--voxel must be in (0, 0.1] (a fraction of the bounds diagonal), got {self.voxel}",
                             None, "use e.g. 0.004")
        if self.trunc is not None and not (math.isfinite(self.trunc) and 1 <= self.trunc <= 100):
            raise InputError(f"--trunc must be in [1, 100] voxels, got {self.trunc}", None, "use e.g. 3")
        if not 0 <= self.min_acc <= 1:
            raise InputError(f"--min-acc must be in [0, 1], got {self.min_acc}", None, "use e.g. 0.5")
        if self.min_views < 1:
            raise InputError(f"--min-views must be at least 1, got {self.min_views}", None, "use e.g. 2")
        if not 0 <= self.min_component < 1:
            raise InputError(f"--min-component must be in [0, 1), got {self.min_component}", None, "use e.g. 0.001")
        if self.neighbours < 1 or self.max_faces < 0:
            raise InputError(f"--neighbours must be >= 1 and --max-faces >= 0, got {self.neighbours}, "
                             f"{self.max_faces}", None, "use e.g. --neighbours 3 --max-faces 200000")
        if self.chunk < 1:
            raise InputError(f"--chunk must be at least 1, got {self.chunk}", None, "use e.g. 4096")


# ---------------------------------------------------------------------- TSDF fusion
@dataclass
class TSDFVolume:
    """A truncated signed distance grid; voxel ``(i, j, k)`` sits at ``origin + voxel * (i, j, k)``."""

    tsdf: Tensor
    """Signed distance over the truncation, in [-1, 1]; positive in front of surfaces, 1 where unobserved.
    ``# [X, Y, Z]`` float32"""
    weight: Tensor
    """Number of observations per voxel (0 = unobserved). ``# [X, Y, Z]`` float32"""
    origin: Tensor
    """Position of voxel (0, 0, 0). ``# [3]`` float64"""
    voxel: float
    """Voxel edge length, scene units."""
    trunc: float
    """Truncation distance, scene units."""

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.tsdf.shape)

    def positions(self, flat: Tensor) -> Tensor:
        """Centres of voxels with flat (C-order) indices ``flat # [P]``. ``# [P, 3]``"""
        X, Y, Z = self.shape
        ijk = torch.stack([flat // (Y * Z), (flat // Z) % Y, flat % Z], -1)
        return self.origin.to(self.tsdf.device) + self.voxel * ijk.to(torch.float64)


def empty_volume(bounds: Tensor, voxel: float, trunc: float, device="cpu") -> TSDFVolume:
    """An unobserved grid over ``bounds # [2, 3]`` padded by ``trunc`` plus 2 voxels on every side, so
    that surfaces on the bounds (a ground plane) get voxels on both sides."""
    pad = trunc + 2 * voxel
    lo = bounds[0].double() - pad
    hi = bounds[1].double() + pad
    dims = torch.ceil((hi - lo) / voxel).long() + 1
    if int(dims.prod()) > 1 << 30:
        raise InputError(f"the TSDF grid would have {int(dims.prod()):,} voxels ({'x'.join(map(str, dims.tolist()))})",
                         None, "use a larger --voxel")
    shape = tuple(int(d) for d in dims)
    return TSDFVolume(torch.ones(shape, device=device), torch.zeros(shape, device=device), lo, voxel, trunc)


def integrate(volume: TSDFVolume, camera: Cameras, depth: Tensor, valid: Tensor | None = None,
              chunk: int = 1 << 20) -> None:
    """Fuse one z-depth map into ``volume`` in place (projective TSDF, nearest pixel, weight 1).

    Every voxel in front of the camera that projects into the image onto a valid pixel of depth
    ``d`` gets the observation ``min(1, (d - z) / trunc)`` unless it lies more than ``trunc``
    behind the surface (``d - z < -trunc``); observations are averaged.

    Args:
        camera: One camera (OpenCV, camera-to-world).
        depth: z-depth per pixel, 0 = none. ``# [H, W]``
        valid: Pixels to use (default: ``depth > 0``). ``# [H, W]`` bool
        chunk: Voxels projected at once.
    """
    dev = volume.tsdf.device
    H, W = depth.shape
    depth = depth.to(dev, torch.float32)
    ok_pix = depth > 0 if valid is None else (valid.to(dev) & (depth > 0))
    depth = torch.where(ok_pix, depth, torch.zeros_like(depth)).reshape(-1)
    w2c = camera.w2c[0].to(dev, torch.float64)
    R, t = w2c[:3, :3], w2c[:3, 3]
    fx, fy, cx, cy = (float(getattr(camera, k)[0]) for k in ("fx", "fy", "cx", "cy"))
    tsdf, weight = volume.tsdf.view(-1), volume.weight.view(-1)
    for start in range(0, tsdf.numel(), chunk):
        flat = torch.arange(start, min(start + chunk, tsdf.numel()), device=dev)
        p = volume.positions(flat) @ R.T + t  # [P, 3] camera frame
        z = p[:, 2]
        zs = z.clamp_min(1e-9)
        col = torch.floor(fx * p[:, 0] / zs + cx)
        row = torch.floor(fy * p[:, 1] / zs + cy)
        inside = (z > 1e-9) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
        flat, z = flat[inside], z[inside].float()
        d = depth[(row[inside] * W + col[inside]).long()]
        sdf = d - z
        use = (d > 0) & (sdf >= -volume.trunc)
        flat, obs = flat[use], (sdf[use] / volume.trunc).clamp(max=1.0)
        w_old = weight[flat]
        tsdf[flat] = (tsdf[flat] * w_old + obs) / (w_old + 1)
        weight[flat] = w_old + 1


def fuse_depths(cameras: Cameras, depths: Tensor, masks: Tensor | None, bounds: Tensor, voxel: float, trunc: float,
                chunk: int = 1 << 20, device="cpu", on_view=None) -> TSDFVolume:
    """TSDF of ``N`` z-depth maps seen by ``cameras`` over ``bounds``.

    Args:
        cameras: ``N`` cameras, the depth maps' resolution.
        depths: z-depth maps, 0 = no depth. ``# [N, H, W]``
        masks: Pixels to fuse (``None``: every pixel with depth). ``# [N, H, W]`` bool
        bounds: ``[min, max]`` corners of the region to reconstruct. ``# [2, 3]``
        voxel: Voxel edge, scene units.
        trunc: Truncation distance, scene units (the reference: 3 voxels).
        on_view: Called with no argument after each view is fused (progress bars).

    Returns:
        The fused :class:`TSDFVolume`.
    """
    if depths.shape[0] != len(cameras) or (masks is not None and masks.shape != depths.shape):
        raise ValueError(f"{len(cameras)} cameras, depths {tuple(depths.shape)}, "
                         f"masks {None if masks is None else tuple(masks.shape)}")
    volume = empty_volume(bounds, voxel, trunc, device)
    for i in range(len(cameras)):
        integrate(volume, cameras[i], depths[i], None if masks is None else masks[i], chunk)
        if on_view is not None:
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
    verts, faces, _, _ = marching_cubes(tsdf, level, allow_degenerate=False)  # verts in voxel units
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


# ---------------------------------------------------------------------- depth rendering
def shifted_cameras(cameras: Cameras, shifts, center: Tensor) -> Cameras:
    """Virtual views: each camera moved along its own x axis by ``s * |centre - camera|`` for each
    shift ``s`` (VolRecon's 25 mm offset), orientation kept. Order: camera-major. ``N * len(shifts)``"""
    out = []
    dist = (cameras.centers - center.to(cameras.c2w)).norm(dim=-1)  # [N]
    for i in range(len(cameras)):
        for s in shifts:
            c2w = cameras.c2w[i:i + 1].clone()
            c2w[0, :3, 3] += c2w[0, :3, 0] * float(s) * dist[i]
            out.append(Cameras(cameras.fx[i:i + 1], cameras.fy[i:i + 1], cameras.cx[i:i + 1], cameras.cy[i:i + 1],
                               c2w, cameras.width, cameras.height))
    return Cameras.cat(out)


def depth_from_outputs(out: dict[str, Tensor], min_acc: float = 0.5) -> tuple[Tensor, Tensor]:
    """z-depth and validity from a model's ``render_view`` outputs. ``# [H, W]`` each.

    ``depth`` is required. With ``acc`` (density models: ``depth = sum_k w_k z_k``) the depth is
    divided by ``acc`` and pixels with ``acc < min_acc`` are invalid; a ``valid`` output (the
    plane-sweep floor: at least 2 views agree) is honoured; non-finite or non-positive depths are
    invalid.
    """
    if "depth" not in out:
        raise InputError("the model renders no depth", None, "mesh a model whose render_rays returns 'depth' "
                         "(IBRNet, GPNR, Omni-Recon or the floor)")
    depth = out["depth"].detach().float()
    valid = torch.isfinite(depth)
    if "acc" in out:
        acc = out["acc"].detach().float()
        valid &= acc >= min_acc
        depth = depth / acc.clamp_min(1e-6)
    if "valid" in out:
        valid &= out["valid"].bool()
    valid &= depth > 0
    return torch.where(valid, depth, torch.zeros_like(depth)).cpu(), valid.cpu()


@torch.no_grad()
def render_depths(model, sources, cameras: Cameras, chunk: int = 4096, min_acc: float = 0.5, device="cpu",
                  on_view=None, fine_pass: bool = True) -> tuple[Tensor, Tensor]:
    """Encode ``sources`` once and render a z-depth map at each camera (``fine_pass``: see ``render_view``).
    ``# [N, H, W]`` depth and valid."""
    features = model.encode(sources.to(device))
    depths, valids = [], []
    for i in range(len(cameras)):
        out = model.render_view(features, cameras[i].to(device=device, dtype=sources.images.dtype), chunk=chunk,
                                fine_pass=fine_pass)
        d, v = depth_from_outputs(out, min_acc)
        depths.append(d)
        valids.append(v)
        if on_view is not None:
            on_view()
    return torch.stack(depths), torch.stack(valids)


# ---------------------------------------------------------------------- cleaning
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


def keep_faces(mesh: trimesh.Trimesh, keep: np.ndarray) -> trimesh.Trimesh:
    """The faces ``keep # [F]`` (bool) of ``mesh`` with unreferenced vertices removed."""
    out = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    out.remove_unreferenced_vertices()
    return out


def visible_faces(mesh: trimesh.Trimesh, cameras: Cameras, masks: np.ndarray | None, voxel: float) -> np.ndarray:
    """Faces hit first by some (in-mask) pixel ray of ``cameras``. ``# [F]`` bool

    The reference casts one ray per pixel at 1600x1200 (~6 rays per voxel edge on DTU); here each
    view is rasterised (both sides of every face) with up to 8 x 8 samples per pixel, enough for 4
    samples per voxel edge at the median depth (2 per edge missed sliver faces and left holes:
    F-score 0.61 vs 0.64 with ground-truth depth), and a sample counts when the pixel it falls in
    is inside the mask.
    """

    seen = np.zeros(len(mesh.faces), dtype=bool)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    for i in range(len(cameras)):
        cam = cameras[i]
        z = verts @ cam.w2c[0, 2, :3].numpy() + float(cam.w2c[0, 2, 3])
        z = np.median(z[z > 0]) if (z > 0).any() else 1.0
        ss = int(np.clip(np.ceil(4 * z / float(cam.fx[0]) / voxel), 1, 8))
        frags = rasterize_mesh(verts, mesh.faces, cam, supersample=ss)
        face = frags.face
        if masks is not None:
            face = np.where(np.repeat(np.repeat(masks[i], ss, 0), ss, 1), face, -1)
        seen[np.unique(face[face >= 0])] = True
    return seen


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


def clean_mesh(mesh: trimesh.Trimesh, cameras: Cameras, masks: Tensor | None, voxel: float,
               options: MeshOptions | None = None) -> tuple[trimesh.Trimesh, dict]:
    """The reference's cleaning (see the module docstring) against the source ``cameras``.

    Args:
        masks: Source-view object masks, or ``None`` (then only hidden faces and small components go).
            ``# [N, H, W]`` bool
        voxel: Voxel size, scene units (sets the rasterisation rate of the hidden-face test).

    Returns:
        The cleaned mesh and the face counts after each step.
    """
    options = options or MeshOptions()
    counts = {"marching_cubes": len(mesh.faces)}
    dilated = None
    if masks is not None:
        dilated = dilate_masks(masks.cpu().numpy().astype(bool), options.dilate * cameras.width)
        votes = mask_votes(np.asarray(mesh.vertices), cameras.to(dtype=torch.float64), dilated)
        inside = votes >= min(options.min_views, len(cameras))
        mesh = keep_faces(mesh, inside[mesh.faces].all(1))
        counts["in_masks"] = len(mesh.faces)
    if options.cull_hidden and len(mesh.faces):
        mesh = keep_faces(mesh, visible_faces(mesh, cameras.to(dtype=torch.float64), dilated, voxel))
        counts["visible"] = len(mesh.faces)
    mesh = drop_small_components(mesh, options.min_component)
    counts["components"] = len(mesh.faces)
    return mesh, counts


# ---------------------------------------------------------------------- the pipeline
@dataclass
class MeshResult:
    """What :func:`mesh_from_model` made."""

    mesh: trimesh.Trimesh
    """The cleaned mesh, scene frame."""
    info: dict
    """Settings, face counts after each step, seconds per stage (JSON-serialisable)."""
    cameras: Cameras
    """The (virtual) cameras the depth maps were rendered at."""
    depths: Tensor
    """The fused z-depth maps, 0 = none. ``# [N, H, W]``"""


def mesh_from_model(model, scene, views, options: MeshOptions | None = None, device="cpu", use_masks: bool = False,
                    progress=None) -> MeshResult:
    """Mesh of ``scene`` from ``model``'s depth renders (see :func:`_mesh_from_model`), the depth maps rendered
    by the pass ``options.depth_pass`` names."""
    options = options or MeshOptions()
    options.check()
    return _mesh_from_model(model, scene, views, options, device, use_masks, progress)


def _mesh_from_model(model, scene, views, options: MeshOptions, device="cpu", use_masks: bool = False,
                     progress=None) -> MeshResult:
    """Mesh of ``scene`` (normalised scene frame) from ``model``'s depth renders with sources ``views``.

    Args:
        model: A :class:`~omnirecon.models.base.GeneralizableModel` whose ``render_rays`` returns ``depth``.
        scene: A :class:`~omnirecon.data.scene.Scene`, normally ``Scene.normalized()``.
        views: Source view indices; every depth map is rendered with all of them as the model's inputs.
        use_masks: Clean with the scene's masks of ``views`` (when it has masks).
        progress: A ``rich.progress.Progress`` to report on (optional).

    Returns:
        A :class:`MeshResult`: the cleaned mesh in the scene frame, a JSON-serialisable record of
        the settings, face counts and seconds per stage, and the depth maps that were fused.
    """

    options = options or MeshOptions()
    options.check()
    if options.fusion == "fit":
        from omnirecon.mesh.fusion import mesh_from_model_fit

        return mesh_from_model_fit(model, scene, views, options, device, use_masks, progress)
    views = list(views)
    model = model.to(device).eval()
    diag = float((scene.bounds[1] - scene.bounds[0]).double().norm())
    voxel = (options.voxel or 1 / 256) * diag
    trunc = (options.trunc or 3.0) * voxel
    src_cams = scene.cameras[views]
    render_cams = shifted_cameras(src_cams, options.shifts, scene.bounds.double().mean(0))
    task = None
    if progress is not None:
        task = progress.add_task("depth", total=2 * len(render_cams) + 2)
    advance = (lambda: progress.advance(task)) if task is not None else None
    seconds = {}
    start = time.perf_counter()
    depths, valid = render_depths(model, Sources.from_scene(scene, views), render_cams, options.chunk, options.min_acc,
                                  device, advance, fine_pass=options.depth_pass == "fine")
    seconds["render"] = time.perf_counter() - start
    if progress is not None:
        progress.update(task, description="fuse")
    start = time.perf_counter()
    volume = fuse_depths(render_cams, depths, valid, scene.bounds, voxel, trunc, options.voxel_chunk, device, advance)
    seconds["fuse"] = time.perf_counter() - start
    if progress is not None:
        progress.update(task, description="marching cubes")
    start = time.perf_counter()
    raw = extract_mesh(volume)
    seconds["marching_cubes"] = time.perf_counter() - start
    if advance:
        advance()
        progress.update(task, description="clean")
    start = time.perf_counter()
    masks = scene.masks[views] if use_masks and scene.masks is not None else None
    mesh, counts = clean_mesh(raw, src_cams, masks, voxel, options)
    seconds["clean"] = time.perf_counter() - start
    if advance:
        advance()
    info = {"views": views, "options": asdict(options), "voxel": voxel, "trunc": trunc, "grid": list(volume.shape),
            "depth_maps": len(render_cams), "valid_depth_fraction": float(valid.float().mean()),
            "masks": masks is not None, "faces": counts, "vertices": len(mesh.vertices), "seconds": seconds}
    return MeshResult(mesh, info, render_cams, depths)


# ---------------------------------------------------------------------- export
def to_input_frame(mesh: trimesh.Trimesh, to_input: Tensor) -> trimesh.Trimesh:
    """``mesh`` moved by the similarity ``to_input # [4, 4]`` (winding flipped if it mirrors)."""
    T = to_input.double().numpy()
    verts = np.asarray(mesh.vertices, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
    faces = np.asarray(mesh.faces)
    if np.linalg.det(T[:3, :3]) < 0:
        faces = faces[:, ::-1]
    return trimesh.Trimesh(verts, faces, process=False)


def check_mesh_paths(paths) -> list[Path]:
    """``paths`` as :class:`Path` objects; :class:`InputError` for an unknown suffix."""
    out = [Path(p) for p in paths]
    for p in out:
        if p.suffix.lower() not in MESH_FORMATS:
            raise InputError(f"cannot write a mesh as {p.suffix or 'a file without suffix'}", p,
                             f"end --out with one of {', '.join(MESH_FORMATS)}")
        if p.is_dir():
            raise InputError("output path is a folder", p, "pass a file name such as mesh.ply")
    return out


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """The sRGB transfer function inverted (IEC 61966-2-1), ``c`` in [0, 1]."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1), ``c`` in [0, 1]."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.clip(c, 0.0031308, None) ** (1 / 2.4) - 0.055)


def gltf_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` as glTF wants it: vertex colours (sRGB bytes, as in our images and PLY files) converted
    to *linear* RGB, since glTF defines ``COLOR_0`` as linear and viewers encode it to sRGB for display
    (sRGB bytes stored as-is show washed out). 8-bit linear is coarse in the shadows: sRGB values
    0-0.1 get only 4 codes (0-3)."""
    if mesh.visual.kind != "vertex":
        return mesh
    rgba = np.asarray(mesh.visual.vertex_colors)
    lin = np.round(srgb_to_linear(rgba[:, :3] / 255.0) * 255).astype(np.uint8)
    out = mesh.copy()
    out.visual = trimesh.visual.ColorVisuals(out, vertex_colors=np.concatenate([lin, rgba[:, 3:]], 1))
    return out


def export_mesh(mesh: trimesh.Trimesh, paths, extra: dict | None = None) -> list[Path]:
    """Write ``mesh`` to every path (PLY binary, OBJ or GLB by suffix), atomically. Vertex colours are sRGB
    bytes in PLY and OBJ and linear in GLB (:func:`gltf_mesh`). ``extra``: ``{path: write(tmp_path)}``, files
    of the same set (metrics, preview) written with the meshes and renamed with them."""
    from omnirecon.outputs import atomic_files  # all written, then renamed: complete or absent

    written = check_mesh_paths(paths)
    extra = extra or {}
    with atomic_files([*written, *extra]) as tmps:
        for (p, write), tmp in zip(extra.items(), tmps[len(written):]):
            write(Path(tmp))
        for p, tmp in zip(written, tmps):
            kind = p.suffix.lower().lstrip(".")
            m = gltf_mesh(mesh) if kind == "glb" else mesh
            data = m.export(file_type=kind, **({"include_normals": False} if kind == "obj" else {}))
            Path(tmp).write_bytes(data if isinstance(data, bytes) else data.encode())
    return written
