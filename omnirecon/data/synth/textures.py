"""Textures: natural photographs bundled with scikit-image and procedural patterns.

A texture is described by a small JSON-serialisable dict (stored in ``scene.json``) and built
deterministically from it by :func:`make_texture`. Surfaces are textured by *triplanar mapping* in
the object's local frame (:func:`sample_triplanar`): the colour of a surface point depends on the
point alone, never on the camera, so every view sees the same colours.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import ndimage
from skimage import data as skdata
from skimage.transform import resize

# scikit-image images that ship inside the wheel (no pooch download needed).
COLOR_PHOTOS = ("astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "immunohistochemistry")
GRAY_PHOTOS = ("brick", "grass", "gravel", "camera", "coins", "moon", "clock", "text", "page")
PATTERNS = ("checker", "stripes", "noise", "dots", "waves")
MIN_WEIGHT = 0.02
"""Triplanar planes weighted below this fraction of the strongest plane are skipped."""


@lru_cache(maxsize=None)
def _photo(name: str) -> np.ndarray:
    """A bundled photograph as float32 RGB in [0, 1] (grey ones replicated). ``# [H, W, 3]``"""
    img = np.asarray(getattr(skdata, name)(), dtype=np.float32) / 255.0
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return img[..., :3]


def random_color(rng: np.random.Generator, light: tuple[float, float] = (0.25, 0.95)) -> list[float]:
    """A saturated-ish random colour, ``[r, g, b]`` in [0, 1]."""
    rgb = colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(0.2, 0.9), rng.uniform(*light))
    return [round(float(c), 4) for c in rgb]


def random_texture(rng: np.random.Generator, photo_prob: float = 0.5) -> dict:
    """Draw a texture descriptor: a photo crop or a procedural pattern."""
    if rng.uniform() < photo_prob:
        names = COLOR_PHOTOS + GRAY_PHOTOS
        name = names[rng.integers(len(names))]
        desc = {"kind": "photo", "name": name, "crop": [round(float(x), 4) for x in rng.uniform(0, 1, 2)],
                "crop_size": round(float(rng.uniform(0.4, 1.0)), 4)}
        if name in GRAY_PHOTOS:
            desc["tint"] = random_color(rng, (0.6, 1.0))
        return desc
    kind = PATTERNS[rng.integers(len(PATTERNS))]
    desc = {"kind": kind, "colors": [random_color(rng) for _ in range(3)],
            "frequency": round(float(rng.uniform(2, 8)), 4), "angle": round(float(rng.uniform(0, np.pi)), 4),
            "seed": int(rng.integers(2**31))}
    return desc


def make_texture(desc: dict, size: int) -> np.ndarray:
    """Build the texture image of a descriptor, ``size x size``, float32 RGB in [0, 1]. ``# [T, T, 3]``"""
    kind = desc["kind"]
    if kind == "photo":
        img = _photo(desc["name"])
        h, w = img.shape[:2]
        side = max(8, int(desc["crop_size"] * min(h, w)))
        y0 = int(desc["crop"][1] * (h - side))
        x0 = int(desc["crop"][0] * (w - side))
        tex = resize(img[y0:y0 + side, x0:x0 + side], (size, size), anti_aliasing=True, order=1)
        if "tint" in desc:
            tex = tex * np.asarray(desc["tint"])
        return np.clip(tex, 0, 1).astype(np.float32)
    colors = np.asarray(desc["colors"], dtype=np.float32)  # [3, 3]
    yy, xx = (np.mgrid[0:size, 0:size] + 0.5) / size  # [T, T] each, in [0, 1)
    a = desc["angle"]
    f = desc["frequency"]
    s = xx * np.cos(a) + yy * np.sin(a)  # rotated coordinate
    t = -xx * np.sin(a) + yy * np.cos(a)
    if kind == "checker":
        k = np.round(f)
        w = ((np.floor(xx * k) + np.floor(yy * k)) % 2)[..., None]
        return _mix(colors[0], colors[1], w)
    if kind == "stripes":
        w = (0.5 + 0.5 * np.sin(2 * np.pi * f * s))[..., None]
        return _mix(colors[0], colors[1], np.clip((w - 0.5) * 4 + 0.5, 0, 1))
    if kind == "waves":
        w = (0.5 + 0.25 * (np.sin(2 * np.pi * f * s) + np.sin(2 * np.pi * f * 0.7 * t + 1.0)))[..., None]
        return _ramp(colors, w)
    rng = np.random.default_rng(desc["seed"])
    if kind == "noise":
        field = np.zeros((size, size))
        for octave in range(4):  # smooth multi-octave noise, wrapped so that it tiles
            sigma = size / (f * 2**octave)
            field += 0.5**octave * ndimage.gaussian_filter(rng.standard_normal((size, size)), sigma, mode="wrap")
        field = (field - field.min()) / max(np.ptp(field), 1e-8)
        return _ramp(colors, field[..., None])
    if kind == "dots":
        n = max(4, int(f * f * 1.5))
        centres = rng.uniform(0, 1, (n, 2))
        radii = rng.uniform(0.3, 0.6, n) / f
        d = np.full((size, size), np.inf)
        for (cx, cy), r in zip(centres, radii):
            dx = np.abs(xx - cx)
            dy = np.abs(yy - cy)
            dist = np.hypot(np.minimum(dx, 1 - dx), np.minimum(dy, 1 - dy)) / r  # wrapped distance
            d = np.minimum(d, dist)
        w = np.clip((1 - d) * size / f / 4, 0, 1)[..., None]  # soft edge of about one texel
        return _mix(colors[0], colors[1], w)
    raise ValueError(f"unknown texture kind {kind!r}")


def _mix(c0: np.ndarray, c1: np.ndarray, w: np.ndarray) -> np.ndarray:
    return ((1 - w) * c0 + w * c1).astype(np.float32)


def _ramp(colors: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Piecewise-linear colour ramp through 3 colours for ``w`` in [0, 1]."""
    lo = _mix(colors[0], colors[1], np.clip(2 * w, 0, 1))
    return np.where(w < 0.5, lo, _mix(colors[1], colors[2], np.clip(2 * w - 1, 0, 1)))


@dataclass
class TextureAtlas:
    """Mip-mapped textures of one scene, flattened for vectorised lookups.

    Level ``l`` of texture ``k`` is stored as a ``2 T_l x 2 T_l`` tile holding the texture and its
    mirror images (``T_l = T / 2^l``), so that mirrored repeat is a wrap-around with a bit mask.
    """

    texels: np.ndarray
    """All tiles, row-major, one after the other. ``# [N, 3]`` float32"""
    offsets: np.ndarray
    """Start of the tile of texture ``k`` at level ``l`` in ``texels``. ``# [K, L]`` int64"""
    size: int
    """``T``, the side of level 0 (a power of two)."""

    @property
    def levels(self) -> int:
        return self.offsets.shape[1]


def make_atlas(textures: list[np.ndarray], min_size: int = 4) -> TextureAtlas:
    """Atlas of ``T x T`` textures (``T`` a power of two) with mip levels down to ``min_size``."""
    size = textures[0].shape[0]
    levels = max(1, int(np.log2(size // min_size)) + 1)
    tiles, offsets, start = [], np.zeros((len(textures), levels), dtype=np.int64), 0
    for k, tex in enumerate(textures):
        for level in range(levels):
            if level:  # 2 x 2 box filter
                tex = 0.25 * (tex[0::2, 0::2] + tex[1::2, 0::2] + tex[0::2, 1::2] + tex[1::2, 1::2])
            top = np.concatenate([tex, tex[:, ::-1]], axis=1)
            tile = np.concatenate([top, top[::-1]], axis=0).reshape(-1, 3)
            offsets[k, level] = start
            start += len(tile)
            tiles.append(tile)
    return TextureAtlas(np.concatenate(tiles).astype(np.float32), offsets, size)


def sample_triplanar(
    atlas: TextureAtlas, tex_id: np.ndarray, position: np.ndarray, normal: np.ndarray, scale: np.ndarray,
    footprint: np.ndarray,
) -> np.ndarray:
    """Colour of surface points by triplanar mapping, mirrored tiling and trilinear mip-mapping.

    Each of the three local coordinate planes projects the texture along one axis; the three
    lookups are blended by ``|n|^4`` of the local normal, which hides seams on curved surfaces and
    gives exact planar mapping on flat faces. The mip level follows the footprint of one image
    sample on the surface, so distant or grazing surfaces are filtered instead of aliased.

    Args:
        atlas: Textures of the scene (:func:`make_atlas`).
        tex_id: Texture index per point. ``# [P]`` int
        position: Local-frame position per point. ``# [P, 3]``
        normal: Local-frame unit shading normal per point. ``# [P, 3]``
        scale: Tile size in local units per point. ``# [P]``
        footprint: Size of one image sample on the surface, local units. ``# [P]``

    Returns:
        RGB albedo. ``# [P, 3]`` float32
    """
    w = normal.astype(np.float32) ** 4  # [P, 3]
    w[w < MIN_WEIGHT * np.maximum(np.maximum(w[:, :1], w[:, 1:2]), w[:, 2:])] = 0  # skip planes that barely contribute
    w /= np.maximum(w[:, :1] + w[:, 1:2] + w[:, 2:], 1e-12)
    uvw = (position / scale[:, None]).astype(np.float32)  # [P, 3] in tiles
    lod = np.clip(np.log2(np.maximum(footprint / scale * atlas.size, 1e-6)), 0, atlas.levels - 1)  # [P]
    lo = np.floor(lod).astype(np.int64)
    t = (lod - lo).astype(np.float32)
    out = np.zeros((len(tex_id), 3), dtype=np.float32)
    # plane k drops axis k; odd offsets keep the three projections from lining up
    for k, (a, b) in enumerate(((1, 2), (0, 2), (0, 1))):
        sel = np.flatnonzero(w[:, k] > 0)
        u, v = uvw[sel, a] + 0.37 * k, uvw[sel, b] + 0.61 * k
        colour = _bilinear(atlas, tex_id[sel], lo[sel], u, v)  # [S, 3]
        blend = np.flatnonzero(t[sel] > 1e-3)  # trilinear: mix in the next coarser level
        if len(blend):
            s2 = sel[blend]
            finer = colour[blend]
            coarser = _bilinear(atlas, tex_id[s2], np.minimum(lo[s2] + 1, atlas.levels - 1), u[blend], v[blend])
            colour[blend] = finer + t[s2, None] * (coarser - finer)
        out[sel] += w[sel, k:k + 1] * colour
    return out


def _bilinear(atlas: TextureAtlas, tex_id: np.ndarray, level: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup with mirrored repeat at a mip level per point; ``u, v`` in tiles. ``# [P, 3]``"""
    half = atlas.size >> level  # [P] texture side at this level
    period = 2 * half  # one texture and its mirror image
    mask = period - 1
    x = u * half - 0.5
    y = v * half - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x0 = x0.astype(np.int64) & mask
    y0 = y0.astype(np.int64) & mask
    x1 = (x0 + 1) & mask
    y1 = (y0 + 1) & mask
    base = atlas.offsets[tex_id, level]
    row0 = base + y0 * period
    row1 = base + y1 * period
    flat = atlas.texels
    top = flat[row0 + x0] * (1 - fx) + flat[row0 + x1] * fx
    bottom = flat[row1 + x0] * (1 - fx) + flat[row1 + x1] * fx
    return top * (1 - fy) + bottom * fy
