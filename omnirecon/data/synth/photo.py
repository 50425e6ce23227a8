"""Realism options of procedural scenes: what a real photograph has and a clean render lacks.

Per scene: a light that varies in colour, strength and ambient share (:func:`scene_light`) and a
view-dependent Blinn-Phong highlight (shaded in :mod:`omnirecon.data.synth.render`). Per view, the
camera pipeline of :func:`camera_effects`, in the order a camera applies it: lens blur, vignetting,
exposure and white-balance gains, sensor noise, clipping (the 8-bit quantisation is the PNG writer's).

Every option is off by default and then changes nothing (files stay byte-identical to scenes written
before the options existed: :func:`options_record` leaves unset options out of ``scene.json``). Each
draws from its own random stream keyed by the scene seed (and the view index), never from the layout's,
so switching one on changes neither the layout nor the other options' draws. Ground truth (depth,
normals, labels, masks, mesh) is unaffected.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.ndimage import gaussian_filter

from omnirecon.data.synth.render import Lighting

REALISM = {"specular": 0.0, "shininess": 32.0, "light_variation": 0.0, "noise": 0.0, "exposure": 0.0,
           "white_balance": 0.0, "vignetting": 0.0, "blur": 0.0}
"""The realism fields of ``SynthOptions`` and their defaults (off)."""
_LIGHT_STREAM, _VIEW_STREAM = 0x11617, 0x5EA1


def options_record(options) -> dict:
    """``SynthOptions`` as recorded in ``scene.json``: realism fields and the aspect only where they differ from the
    default (the files of a scene without them stay those written before they existed)."""
    record = dataclasses.asdict(options)
    for name, default in {**REALISM, "aspect": 1.0}.items():
        if record.get(name) == default:
            record.pop(name, None)
    return record


def scene_light(light: Lighting, options, seed: int) -> Lighting:
    """The layout's light with the scene's highlight and, with ``light_variation = v > 0``, a random
    colour tint (per-channel log-gain std 0.15 v, normalised to mean 1), intensity (log std 0.3 v) and
    ambient share (+- 0.15 v, kept in [0.05, 0.9])."""
    out = light
    if options.specular > 0:
        out = dataclasses.replace(out, specular=float(options.specular), shininess=float(options.shininess))
    v = options.light_variation
    if v > 0:
        rng = np.random.default_rng([seed, _LIGHT_STREAM])
        gain = np.exp(rng.normal(0.0, 0.15 * v, 3))
        out = dataclasses.replace(
            out, color=tuple(round(float(g), 6) for g in gain / gain.mean()),
            intensity=round(float(out.intensity * np.exp(rng.normal(0.0, 0.3 * v))), 6),
            ambient=round(float(np.clip(out.ambient + rng.uniform(-0.15, 0.15) * v, 0.05, 0.9)), 6))
    return out


def camera_effects(rgb: np.ndarray, options, seed: int, view: int) -> np.ndarray:
    """Apply the per-view camera options to a rendered ``rgb # [H, W, 3]`` float in [0, 1]; the same
    array when every one is off.

    - ``blur = s``: Gaussian blur of std ``s`` pixels (edges replicated).
    - ``vignetting = v``: gain ``1 - v r^2``, ``r`` the distance from the image centre, 1 at the corners.
    - ``exposure = e``: one gain ``2^N(0, e)`` per view (stops).
    - ``white_balance = w``: per-channel gains ``exp(N(0, w))`` per view, normalised to mean 1.
    - ``noise = n``: Gaussian noise of std ``sqrt((n^2) x value + (n / 4)^2)`` per pixel and channel
      (shot noise plus a read-noise floor).
    """
    if all(getattr(options, k) == 0 for k in ("blur", "vignetting", "exposure", "white_balance", "noise")):
        return rgb
    rng = np.random.default_rng([seed, _VIEW_STREAM, view])
    img = rgb.astype(np.float64)
    h, w = img.shape[:2]
    if options.blur > 0:
        img = gaussian_filter(img, sigma=(options.blur, options.blur, 0), mode="nearest")
    if options.vignetting > 0:
        y, x = np.mgrid[0:h, 0:w]
        r2 = (((x + 0.5) / w - 0.5) ** 2 + ((y + 0.5) / h - 0.5) ** 2) / 0.5
        img = img * (1.0 - options.vignetting * r2)[..., None]
    exposure = 2.0 ** rng.normal(0.0, options.exposure) if options.exposure > 0 else 1.0
    balance = np.exp(rng.normal(0.0, options.white_balance, 3)) if options.white_balance > 0 else np.ones(3)
    img = img * (exposure * balance / balance.mean())
    if options.noise > 0:
        std = np.sqrt(options.noise**2 * np.clip(img, 0, None) + (options.noise / 4) ** 2)
        img = img + std * rng.standard_normal(img.shape)
    return np.clip(img, 0.0, 1.0).astype(np.float32)
