"""Lambertian shading of a triangle soup (NumPy, float64) on the exact z-buffer of
:mod:`omnirecon.render.zbuffer`.

Each view is rasterized exactly (supersampled at the edges) and shaded per sample.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnirecon.data.synth.textures import TextureAtlas, sample_triplanar
from omnirecon.render.zbuffer import Fragments, rasterize


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
class Lighting:
    """A directional light fixed in the world plus ambient light, and an optional white Blinn-Phong
    highlight (the one view-dependent term; off by default)."""

    direction: np.ndarray
    """Unit vector from surfaces towards the light, world frame. ``# [3]``"""
    ambient: float
    """Ambient fraction in [0, 1]; the rest is Lambertian."""
    intensity: float = 1.0
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Light colour (per-channel gain)."""
    specular: float = 0.0
    """Strength of the highlight ``specular * intensity * max(0, n . h)^shininess`` (0: Lambertian only)."""
    shininess: float = 32.0
    """Blinn-Phong exponent."""


def shade(mesh: Mesh, frags: Fragments, K: np.ndarray, w2c: np.ndarray, light: Lighting,
          background: np.ndarray) -> np.ndarray:
    """Lambertian + ambient colour of a visibility buffer. ``# [H, W, 3]`` float32 in [0, 1]

    ``colour = albedo * intensity * (ambient + (1 - ambient) * max(0, n . l))`` (times the light colour,
    plus ``specular * intensity * max(0, n . h)^shininess`` where the surface is lit) with the smooth
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
    colour = albedo * light.intensity * (light.ambient + (1 - light.ambient) * lambert)
    tint = np.asarray(light.color, dtype=np.float32)
    if (tint != 1).any():
        colour = colour * tint
    if light.specular > 0:  # Blinn-Phong: half vector between the light and the direction to the camera
        half = _normalize(light.direction.astype(np.float32)[None] - ray)
        spec = np.maximum(np.einsum("pc,pc->p", normal, half), 0) ** light.shininess * (lambert[:, 0] > 0)
        colour = colour + (light.specular * light.intensity * spec)[:, None] * tint
    image[hit] = np.clip(colour, 0, 1)
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
