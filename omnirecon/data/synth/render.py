"""Vectorised z-buffer rasterizer and Lambertian shading of a triangle soup (NumPy, float64).

The rasterizer finds, for every sample point of the image, the nearest triangle whose projection
covers it, with the perspective-correct barycentrics of the hit: a visibility buffer. Depth is
``1 / (sum_k b_k / z_k)``, which is exact for a planar triangle (``1/z`` is affine in the image),
so the depth and positions written out lie on the exported mesh up to float64 rounding.

Work per view is proportional to the number of triangles plus the pixels their bounding boxes
cover: each triangle's bounding box is expanded into candidate samples, the samples inside all
three edges are kept, and the nearest one per sample wins (``np.minimum.at``; ties go to the
lower triangle index, so the result is deterministic).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnirecon.data.synth.textures import TextureAtlas, sample_triplanar


@dataclass
class Mesh:
    """A scene's triangles with everything the shader needs, all in the world (scene) frame."""

    vertices: np.ndarray
    """``# [V, 3]`` float64 (values are exactly representable in float32, like the PLY file)"""
    faces: np.ndarray
    """``# [F, 3]`` int64"""
    face_label: np.ndarray
    """Label id per face (objects 1..254, ground 255). ``# [F]`` uint8"""
    face_normal: np.ndarray
    """Unit geometric normal per face. ``# [F, 3]`` float64"""
    corner_attr: np.ndarray
    """Per face corner: world shading normal (3), object-local position (3) and local shading
    normal (3). ``# [F, 3, 9]`` float32"""
    face_texture: np.ndarray
    """Texture index per face into the atlas. ``# [F]`` int64"""
    face_tile: np.ndarray
    """Texture tile size per face, local units. ``# [F]`` float32"""
    atlas: TextureAtlas
    """Mip-mapped textures, one per object and one for the ground."""


@dataclass
class Fragments:
    """Visibility buffer of one view: nearest triangle per sample."""

    face: np.ndarray
    """Triangle index, -1 where nothing is hit. ``# [H, W]`` int64"""
    bary: np.ndarray
    """Perspective-correct barycentrics (sum to 1). ``# [H, W, 3]`` float64"""
    depth: np.ndarray
    """Camera-frame z of the hit, 0 where nothing is hit. ``# [H, W]`` float64"""


def rasterize(
    vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, w2c: np.ndarray, width: int, height: int,
    near: float = 1e-6,
) -> Fragments:
    """Visibility buffer of a triangle mesh seen by one pinhole camera (OpenCV frame).

    Samples sit at pixel centres ``(j + 0.5, i + 0.5)``; render at ``s`` samples per pixel side by
    scaling ``K`` (``fx, fy, cx, cy`` times ``s``) and the size. Back faces (normal pointing away
    from the camera) are skipped, so meshes must be closed and outward-facing, or one-sided
    surfaces seen from their front (the ground).

    Args:
        vertices: World positions. ``# [V, 3]`` float64
        faces: ``# [F, 3]`` int
        K: Intrinsics. ``# [3, 3]``
        w2c: World-to-camera rigid transform. ``# [4, 4]``
        width, height: Image size in samples.
        near: Every vertex must lie at camera z > ``near`` (the generator keeps content in front of
            all cameras; nothing is clipped here).
    """
    cam = vertices @ w2c[:3, :3].T + w2c[:3, 3]  # [V, 3]
    z = cam[:, 2]
    if z.min() <= near:
        raise ValueError("a vertex lies behind the camera; the scene layout must keep content in front")
    uv = cam[:, :2] / z[:, None] * K[[0, 1], [0, 1]] + K[[0, 1], [2, 2]]  # [V, 2]
    tri = uv[faces]  # [F, 3, 2]
    tz = z[faces]  # [F, 3]
    # Front faces: geometric normal towards the camera (camera centre is the origin of `cam`).
    p0 = cam[faces[:, 0]]
    normal = np.cross(cam[faces[:, 1]] - p0, cam[faces[:, 2]] - p0)  # [F, 3]
    front = np.einsum("fc,fc->f", normal, p0) < 0
    u, v = tri[..., 0], tri[..., 1]  # [F, 3] each
    j0 = np.maximum(np.ceil(np.minimum(np.minimum(u[:, 0], u[:, 1]), u[:, 2]) - 0.5), 0).astype(np.int64)  # [F]
    j1 = np.minimum(np.floor(np.maximum(np.maximum(u[:, 0], u[:, 1]), u[:, 2]) - 0.5), width - 1).astype(np.int64)
    i0 = np.maximum(np.ceil(np.minimum(np.minimum(v[:, 0], v[:, 1]), v[:, 2]) - 0.5), 0).astype(np.int64)
    i1 = np.minimum(np.floor(np.maximum(np.maximum(v[:, 0], v[:, 1]), v[:, 2]) - 0.5), height - 1).astype(np.int64)
    nx, ny = j1 - j0 + 1, i1 - i0 + 1
    area = _edge(tri[:, 0], tri[:, 1], tri[:, 2])  # [F], 2x signed area in the image
    keep = np.flatnonzero(front & (nx > 0) & (ny > 0) & (np.abs(area) > 1e-12))

    # Barycentrics are affine in (u, v): b_k = A[f, k] . (u, v, 1).
    t = tri[keep]
    A = np.empty((len(keep), 3, 3))
    for k in range(3):
        a, b = t[:, (k + 1) % 3], t[:, (k + 2) % 3]  # edge opposite vertex k
        A[:, k, 0] = -(b[:, 1] - a[:, 1])
        A[:, k, 1] = b[:, 0] - a[:, 0]
        A[:, k, 2] = (b[:, 1] - a[:, 1]) * a[:, 0] - (b[:, 0] - a[:, 0]) * a[:, 1]
    A /= area[keep][:, None, None]

    # Expand every bounding box into candidate samples and keep those inside all three edges.
    counts = (nx * ny)[keep]
    owner = np.repeat(np.arange(len(keep)), counts)  # [C] index into keep
    offset = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
    width_k = nx[keep][owner]
    col = j0[keep][owner] + offset % width_k
    row = i0[keep][owner] + offset // width_k
    M = A[owner]  # [C, 3, 3]
    bary = M[:, :, 0] * (col[:, None] + 0.5) + M[:, :, 1] * (row[:, None] + 0.5) + M[:, :, 2]  # [C, 3]
    inside = np.flatnonzero((bary[:, 0] >= -1e-10) & (bary[:, 1] >= -1e-10) & (bary[:, 2] >= -1e-10))
    owner, bary = owner[inside], bary[inside]
    pix = row[inside] * width + col[inside]
    inv_z = bary / tz[keep[owner]]  # [S, 3]; 1/z is affine in the image too
    depth = 1.0 / (inv_z[:, 0] + inv_z[:, 1] + inv_z[:, 2])

    # Z-buffer: nearest depth per sample, ties to the lowest triangle index.
    zbuf = np.full(width * height, np.inf)
    np.minimum.at(zbuf, pix, depth)
    win = np.flatnonzero(depth == zbuf[pix])
    first = np.full(width * height, np.iinfo(np.int64).max)
    np.minimum.at(first, pix[win], win)
    hit = np.flatnonzero(first < np.iinfo(np.int64).max)
    best = first[hit]

    face = np.full(width * height, -1, dtype=np.int64)
    face[hit] = keep[owner[best]]
    bary_out = np.zeros((width * height, 3))
    bary_out[hit] = inv_z[best] * depth[best][:, None]  # perspective-correct
    zout = np.zeros(width * height)
    zout[hit] = depth[best]
    return Fragments(face.reshape(height, width), bary_out.reshape(height, width, 3), zout.reshape(height, width))


def _edge(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Edge function ``(b - a) x (p - a)`` of 2D points. ``# [...]``"""
    return (b[..., 0] - a[..., 0]) * (p[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (p[..., 0] - a[..., 0])


@dataclass
class Lighting:
    """A directional light fixed in the world plus ambient light (view-independent shading)."""

    direction: np.ndarray
    """Unit vector from surfaces towards the light, world frame. ``# [3]``"""
    ambient: float
    """Ambient fraction in [0, 1]; the rest is Lambertian."""
    intensity: float = 1.0


def shade(mesh: Mesh, frags: Fragments, K: np.ndarray, w2c: np.ndarray, light: Lighting,
          background: np.ndarray) -> np.ndarray:
    """Lambertian + ambient colour of a visibility buffer. ``# [H, W, 3]`` float32 in [0, 1]

    ``colour = albedo * intensity * (ambient + (1 - ambient) * max(0, n . l))`` with the smooth
    shading normal ``n`` and the triplanar albedo: a function of the surface point only, apart
    from the texture filtering, which widens with the footprint of a sample on the surface
    (``z / f / sqrt(|cos|)``, between the isotropic and the along-the-slope widths).

    Args:
        K, w2c: The camera the fragments were rasterized with (``K`` at the sample rate).
    """
    h, w = frags.face.shape
    image = np.empty((h * w, 3), dtype=np.float32)
    image[:] = background
    face = frags.face.reshape(-1)
    hit = np.flatnonzero(face >= 0)
    f = face[hit]
    b = frags.bary.reshape(-1, 3)[hit].astype(np.float32)  # [P, 3]
    attr = np.einsum("pk,pkc->pc", b, mesh.corner_attr[f])  # [P, 9]
    normal = _normalize(attr[:, 0:3])
    # ray direction per sample (camera frame, then world) for the footprint's slant
    v, u = np.divmod(hit, w)
    ray = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones(len(hit))], axis=1)
    ray = _normalize(ray.astype(np.float32) @ w2c[:3, :3].astype(np.float32))  # row-vector @ R = R^T ray
    cos = np.maximum(np.abs(np.einsum("pc,pc->p", ray, normal)), 0.05)
    z = frags.depth.reshape(-1)[hit].astype(np.float32)
    footprint = z / float(K[0, 0]) / np.sqrt(cos)
    albedo = sample_triplanar(mesh.atlas, mesh.face_texture[f], attr[:, 3:6], _normalize(attr[:, 6:9]),
                              mesh.face_tile[f], footprint)
    lambert = np.maximum(normal @ light.direction.astype(np.float32), 0)[:, None]
    image[hit] = np.clip(albedo * light.intensity * (light.ambient + (1 - light.ambient) * lambert), 0, 1)
    return image.reshape(h, w, 3)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.sqrt(np.einsum("pc,pc->p", v, v)), 1e-12)[:, None]


def render_view(
    mesh: Mesh, K: np.ndarray, w2c: np.ndarray, width: int, height: int, light: Lighting,
    background: np.ndarray, supersample: int = 1,
) -> dict[str, np.ndarray]:
    """Render one view: RGB and the ground truth at pixel centres.

    With ``supersample = s > 1`` the RGB image averages an ``s x s`` grid of samples per pixel
    (anti-aliasing); depth, normals and labels always come from one sample at the pixel centre.

    Returns:
        ``rgb # [H, W, 3]`` float32, ``depth # [H, W]`` float64 (camera z, 0 = none),
        ``normal # [H, W, 3]`` float64 (world-frame geometric normal, 0 = none),
        ``label # [H, W]`` uint8 (0 = none), ``face # [H, W]`` int64 (-1 = none).
    """
    centre = rasterize(mesh.vertices, mesh.faces, K, w2c, width, height)
    if supersample > 1:
        Ks = K.copy()
        Ks[:2] *= supersample
        fine = rasterize(mesh.vertices, mesh.faces, Ks, w2c, width * supersample, height * supersample)
        rgb = shade(mesh, fine, Ks, w2c, light, background)
        rgb = sum(rgb[i::supersample, j::supersample] for i in range(supersample) for j in range(supersample))
        rgb = rgb / supersample**2  # box filter over the s x s samples of each pixel
    else:
        rgb = shade(mesh, centre, K, w2c, light, background)
    hit = centre.face >= 0
    normal = np.zeros((height, width, 3))
    normal[hit] = mesh.face_normal[centre.face[hit]]
    label = np.zeros((height, width), dtype=np.uint8)
    label[hit] = mesh.face_label[centre.face[hit]]
    return {"rgb": rgb, "depth": centre.depth, "normal": normal, "label": label, "face": centre.face}
