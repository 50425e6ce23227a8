"""Editing by predict-then-blend (Omni-Recon §9 without a diffusion model): pick an object by its label,
edit it in every source image, re-blend the edited sources into novel views; and edit the baked mesh.

1. **Pick.** An object is a label value of the per-view label maps (``scene.labels`` or a 2-D
   segmenter's argmax); a click ``(x, y)`` in a view becomes the label under it (:func:`label_at`).
2. **Edit the sources.** :func:`recolour` keeps each pixel's HSV value (shading, texture) and takes the
   hue and saturation of the new colour; :func:`remove` paints the pixels (dilated by ``dilate`` px, to
   cover anti-aliased rims) with the background colour or inpaints them (scikit-image's biharmonic
   inpainting).
3. **Re-blend** (:func:`reblend_volumetric`, :func:`reblend_mesh`). By default the blend weights are
   those of the *unedited* sources and the edited images are blended with them as a signal: a pixel
   changes only if one of its blended samples reads an edited source pixel, so other objects stay
   exactly as rendered (up to boundary pixels). ``after_features`` / ``after`` renderer from the
   *edited* sources re-run the whole model instead (the paper's loop: new features, and on the
   volumetric path new geometry, which is what makes a removed object's depth go away).
4. **Geometry.** :func:`coloured_mesh` bakes one colour per face; :func:`edit_faces` deletes or
   recolours the faces of a label (face labels: :func:`omnirecon.lift.surface.face_labels`); the result
   exports as GLB (trimesh; colours as vertex colours of unmerged faces).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
import trimesh
from torch import Tensor

from omnirecon.errors import InputError
from omnirecon.lift.blend import normalise

Action = Literal["recolour", "remove"]
Fill = Literal["background", "inpaint"]


# ---------------------------------------------------------------------- pick
def label_at(label_maps, view: int, x: int, y: int) -> int:
    """The label value at column ``x``, row ``y`` of view ``view`` of ``label_maps # [N, H, W]``."""
    N, H, W = label_maps.shape
    if not 0 <= view < N:
        raise InputError(f"click view {view} outside the views 0..{N - 1}", None, "pick a view of the scene")
    if not (0 <= x < W and 0 <= y < H):
        raise InputError(f"click ({x}, {y}) outside the {W}x{H} image", None, "x is the column, y the row")
    return int(label_maps[view, y, x])


# ---------------------------------------------------------------------- edit the sources
def recolour(images: Tensor, masks: Tensor, colour) -> Tensor:
    """``images # [N, H, W, 3]`` with the pixels of ``masks # [N, H, W]`` given the hue and saturation of
    ``colour`` (RGB in [0, 1]), their HSV value kept. ``# [N, H, W, 3]``"""
    from skimage.color import hsv2rgb, rgb2hsv

    img = images.detach().cpu().double().numpy().clip(0, 1)
    m = masks.cpu().numpy().astype(bool)
    hsv = rgb2hsv(img.reshape(-1, 1, 3)).reshape(img.shape)
    target = rgb2hsv(np.asarray(colour, np.float64).reshape(1, 1, 3))[0, 0]
    hsv[m, 0], hsv[m, 1] = target[0], target[1]
    out = hsv2rgb(hsv.reshape(-1, 1, 3)).reshape(img.shape)
    return torch.from_numpy(np.where(m[..., None], out, img)).to(images.dtype)


def dilate(masks: Tensor, pixels: int) -> Tensor:
    """``masks # [N, H, W]`` grown by ``pixels`` (4-neighbourhood steps)."""
    from scipy.ndimage import binary_dilation

    m = masks.cpu().numpy().astype(bool)
    if pixels <= 0:
        return torch.from_numpy(m)
    return torch.from_numpy(np.stack([binary_dilation(v, iterations=pixels) for v in m]))


def remove(images: Tensor, masks: Tensor, fill: Fill = "background", background=(1.0, 1.0, 1.0),
           dilation: int = 1) -> Tensor:
    """``images # [N, H, W, 3]`` with the pixels of ``masks # [N, H, W]`` (grown by ``dilation`` px) set to
    ``background`` or inpainted (biharmonic, per view). ``# [N, H, W, 3]``"""
    m = dilate(masks, dilation).numpy()
    img = images.detach().cpu().double().numpy().copy()
    if fill == "background":
        img[m] = np.asarray(background, np.float64)
    elif fill == "inpaint":
        from skimage.restoration import inpaint_biharmonic

        for i in range(len(img)):
            if m[i].any() and not m[i].all():
                img[i] = inpaint_biharmonic(img[i], m[i], channel_axis=-1)
    else:
        raise ValueError(f"fill must be 'background' or 'inpaint', got {fill!r}")
    return torch.from_numpy(img.clip(0, 1)).to(images.dtype)


def edit_images(images: Tensor, masks: Tensor, action: Action, colour=(0.9, 0.1, 0.1), fill: Fill = "background",
                background=(1.0, 1.0, 1.0), dilation: int = 1) -> Tensor:
    """:func:`recolour` or :func:`remove` the pixels of ``masks`` in every image. ``# [N, H, W, 3]``"""
    if action == "recolour":
        return recolour(images, masks, colour)
    if action == "remove":
        return remove(images, masks, fill, background, dilation)
    raise ValueError(f"action must be 'recolour' or 'remove', got {action!r}")


# ---------------------------------------------------------------------- re-blend
def reblend_volumetric(model, features, camera, images: Tensor, edited: Tensor, onehot: Tensor,
                       after_features=None, chunk: int = 4096) -> dict[str, Tensor]:
    """Render one target before and after the edit on the volumetric path. ``images, edited # [K, H, W, 3]``
    (original and edited sources, in the order of ``features``), ``onehot # [K, H, W, C]`` (their labels).

    Returns ``before, after # [H, W, 3]`` (raw composites ``sum_s w_s sum_i omega_si c_i``: ``before`` is
    the model's RGB), ``labels # [H, W, C]`` (lifted, normalised) and ``weight # [H, W]``. ``after`` blends
    ``edited`` with the weights of ``features``, or with those of ``after_features`` (encoded from the
    edited sources: the model re-run)."""
    src = features.sources.images
    cam = camera.to(device=src.device, dtype=src.dtype)
    ones = torch.ones(*images.shape[:3], 1)
    parts = [ones, images.float(), onehot.float()] + ([edited.float()] if after_features is None else [])
    stacked = torch.cat(parts, -1).to(src.device, src.dtype)  # [K, H, W, 1 + 3 + C (+ 3)]
    sig = model.render_view(features, cam, chunk=chunk, signals=stacked)["signal"].float().cpu()
    C = onehot.shape[-1]
    weight = sig[..., 0]
    out = {"before": sig[..., 1:4], "labels": normalise(sig[..., 4:4 + C], weight, "probabilities"), "weight": weight}
    if after_features is None:
        out["after"] = sig[..., 4 + C:]
    else:
        asrc = after_features.sources.images
        out["after"] = model.render_view(after_features, cam, chunk=chunk,
                                         signals=edited.to(asrc.device, asrc.dtype))["signal"].float().cpu()
    return out


def reblend_mesh(renderer, camera, images: Tensor, edited: Tensor, onehot: Tensor, after=None) -> dict[str, Tensor]:
    """:func:`reblend_volumetric` on the mesh path: ``renderer`` (a ``MeshRenderer`` of the original sources)
    gives ``before``, ``labels`` and ``weight`` (1 where the mesh covers the pixel); ``after`` blends
    ``edited`` with the weights of ``renderer``, or of the renderer that ``after()`` opens (of the edited
    sources and/or an edited mesh). Uncovered pixels take each renderer's background colour.

    ``after`` is a factory, opened only once ``renderer`` has drawn its last frame: a rasterizer whose GL
    context was created before another live one draws into the wrong context (raster.py makes no context
    current before drawing)."""
    surf, values = _mesh_blend(renderer, camera, torch.cat([images.float(), onehot.float()], -1))
    bg = torch.tensor(renderer.options.background, dtype=values.dtype, device=values.device)
    weight = surf.image(torch.ones_like(values[:, :1]), 0.0)[..., 0].float().cpu()
    out = {"before": surf.image(values[:, :3], bg).float().cpu(), "weight": weight,
           "labels": normalise(surf.image(values[:, 3:], 0.0).float().cpu(), weight, "probabilities")}
    if after is None:
        surf2, values2 = _mesh_blend(renderer, camera, edited.float())
        out["after"] = surf2.image(values2, bg).float().cpu()
        return out
    with after() as r2:
        surf2, values2 = _mesh_blend(r2, camera, edited.float())
        bg2 = torch.tensor(r2.options.background, dtype=values2.dtype, device=values2.device)
        out["after"] = surf2.image(values2, bg2).float().cpu()
    return out


def _mesh_blend(renderer, camera, maps: Tensor):
    """The covered pixels of ``camera`` and ``maps # [K, H, W, C]`` blended there. ``# [P, C]``"""
    with torch.inference_mode():
        shaded = renderer.weights(camera, with_coords=True)
        return shaded.surface, renderer.blend(shaded, maps.to(renderer.device, renderer.dtype).permute(0, 3, 1, 2))


# ---------------------------------------------------------------------- geometry
def coloured_mesh(mesh: trimesh.Trimesh, face_colours: np.ndarray) -> trimesh.Trimesh:
    """A copy of ``mesh`` with one colour per face (``# [F, 3]`` in [0, 1]) as vertex colours of unmerged
    faces (each face its own three vertices: GLB has no face colours)."""
    faces = np.asarray(mesh.faces)
    verts = np.asarray(mesh.vertices)[faces.reshape(-1)]
    rgba = np.concatenate([np.clip(face_colours, 0, 1), np.ones((len(faces), 1))], 1)
    colours = (np.repeat(rgba, 3, axis=0) * 255 + 0.5).astype(np.uint8)
    return trimesh.Trimesh(verts, np.arange(3 * len(faces)).reshape(-1, 3), vertex_colors=colours, process=False)


def edit_faces(mesh: trimesh.Trimesh, face_colours: np.ndarray, labels: np.ndarray, target: int, action: Action,
               colour=(0.9, 0.1, 0.1)) -> tuple[trimesh.Trimesh, np.ndarray, np.ndarray]:
    """Delete (``remove``) or recolour the faces whose label is ``target``. Returns the edited mesh, its face
    colours ``# [F', 3]`` and the kept face indices into ``mesh`` ``# [F']``."""
    hit = np.asarray(labels) == target
    colours = np.asarray(face_colours, np.float64)
    if action == "remove":
        keep = np.flatnonzero(~hit)
        out = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces)[keep], process=False)
        out.remove_unreferenced_vertices()
        return out, colours[keep], keep
    if action == "recolour":
        new = colours.copy()
        if hit.any():
            new[hit] = recolour(torch.from_numpy(colours[hit])[None, None], torch.ones(1, 1, int(hit.sum()), dtype=torch.bool),
                                colour)[0, 0].numpy()
        return mesh.copy(), new, np.arange(len(colours))
    raise ValueError(f"action must be 'recolour' or 'remove', got {action!r}")
