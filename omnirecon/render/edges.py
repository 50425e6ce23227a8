"""Depth edges of a rendered view, and softening the colour there (not in the paper).

A mesh's depth edges (an object's outline against what lies behind it, a blade on a brick) sit about a pixel
away from the photo's: the meshes come from stereo matched with blocks a few pixels wide and fused in voxels about
half a pixel across. A pixel beside such an edge takes the colour of one side where the photo shows the other, and
these pixels carry a large part of the error of a held-out view (on dtu_scan37 the pixels within 2 px of the
mesh's depth edges carry a share of the object mask's squared error about twice their share of its pixels). Where the side is uncertain, the mean
of the two sides' colours is the better guess (the squared error of a wrong hard choice is four times that of the
mean), so :func:`soften_edges` blurs the rendered colour at the depth edges only: the rest of the image keeps its
sharpness (a blur of the whole image lowered dtu_scan37's held-out mask PSNR).

:func:`depth_edges` finds the edges from the rendered z-depth alone: a pixel is on an edge where the inverse depth
bends between it and its two neighbours along a row, a column or a diagonal (on a plane the inverse depth is linear
in the image, so a slanted surface is not an edge however steep), or where the mesh covers it and not a neighbour
(or the other way: the outline).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

SOFTEN = 0.7
"""The default blur at depth edges in pixels (``finetune --soften``, ``MeshRenderOptions.soften`` of the real-time
renders that follow finetune's record; why this value: ``FinetuneConfig.soften``)."""
EDGE_BEND = 0.02
""":func:`depth_edges`: the relative bend of the inverse depth over three pixels (``|1/z_a + 1/z_b - 2/z| z``) above
which a pixel is on a depth edge. Of the bends 0.01, 0.02 and 0.04 (held-out PSNR with :func:`soften_edges` at 0.7
px, before tuning, on the bench meshes of dtu_scan37, fern and the demo scene) 0.02 was best or near it on each; a
3x3 window's largest over smallest depth instead (slanted surfaces count) scored lower on fern and the demo."""


def depth_edges(depth: Tensor, bend: float = EDGE_BEND) -> Tensor:
    """Pixels of a rendered z-depth image ``depth # [H, W]`` (0: no surface) on a depth edge (module docstring):
    the inverse depth bends by more than ``bend`` (relative) along a row, a column or a diagonal through the pixel,
    or the pixel and one of those neighbours disagree on whether there is a surface. ``# [H, W]`` bool"""
    if _host(depth):
        return _depth_edges_cv2(depth, bend)
    H, W = depth.shape
    has = depth > 0  # [H, W]
    inv = torch.where(has, 1 / depth.clamp_min(1e-12), torch.zeros_like(depth))  # [H, W]
    inv_p = F.pad(inv[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]  # [H + 2, W + 2]
    has_p = F.pad(has[None, None].float(), (1, 1, 1, 1), mode="replicate")[0, 0] > 0  # [H + 2, W + 2]
    inside = F.pad(torch.ones(1, 1, H, W, dtype=torch.bool, device=depth.device), (1, 1, 1, 1))[0, 0]  # [H + 2, W + 2]
    edge = torch.zeros_like(has)
    for (ai, aj), (bi, bj) in (((1, 0), (1, 2)), ((0, 1), (2, 1)), ((0, 0), (2, 2)), ((0, 2), (2, 0))):
        za, zb = inv_p[ai:ai + H, aj:aj + W], inv_p[bi:bi + H, bj:bj + W]  # the two neighbours [H, W]
        ha, hb = has_p[ai:ai + H, aj:aj + W], has_p[bi:bi + H, bj:bj + W]
        both = inside[ai:ai + H, aj:aj + W] & inside[bi:bi + H, bj:bj + W]  # no bend across the image border
        bent = (za + zb - 2 * inv).abs() > bend * inv
        edge |= (has & ha & hb & both & bent) | (has != ha) | (has != hb)
    return edge


def _depth_edges_cv2(depth: Tensor, bend: float) -> Tensor:
    """:func:`depth_edges` on the CPU through OpenCV, its twin (equal): the second difference of the inverse depth
    along each of the four directions as one 3x3 filter, cleared where a neighbour lies outside the image, and the
    coverage outline as a 3x3 dilation unequal to the erosion (the border replicated). ``# [H, W]`` bool"""
    import cv2

    d = depth.contiguous().numpy()
    has = d > 0  # [H, W]
    inv = np.where(has, 1 / np.maximum(d, 1e-12), 0).astype(d.dtype)  # [H, W]
    limit = bend * inv
    bent = np.zeros(d.shape, bool)
    for a, b in (((1, 0), (1, 2)), ((0, 1), (2, 1)), ((0, 0), (2, 2)), ((0, 2), (2, 0))):
        k = np.zeros((3, 3), d.dtype)
        k[a], k[b], k[1, 1] = 1, 1, -2
        second = np.abs(cv2.filter2D(inv, -1, k, borderType=cv2.BORDER_REPLICATE)) > limit  # [H, W]
        if a[0] != 1:  # a neighbour above and below: none across the top and bottom rows
            second[[0, -1]] = False
        if a[1] != 1:  # left and right
            second[:, [0, -1]] = False
        bent |= second
    u8 = has.view(np.uint8)
    square = np.ones((3, 3), np.uint8)
    outline = cv2.dilate(u8, square, borderType=cv2.BORDER_REPLICATE) != cv2.erode(u8, square, borderType=cv2.BORDER_REPLICATE)
    return torch.from_numpy(outline | (has & bent))


def gaussian_blur(image: Tensor, sigma: float) -> Tensor:
    """``image # [H, W, C]`` blurred by a Gaussian of ``sigma`` pixels (a 5x5 kernel up to sigma 1, wider beyond;
    the border replicated). ``# [H, W, C]``

    Separable. On the CPU without autograd, OpenCV's ``sepFilter2D`` with the same kernel; elsewhere its twin
    :func:`_shifted_blur` (the same sums up to float rounding)."""
    r = max(2, int(round(3 * sigma)))
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-x * x / (2 * sigma * sigma))
    g = g / g.sum()  # [2r + 1]
    if _host(image):
        import cv2

        k = g.to(image.dtype).numpy()[:, None]
        out = cv2.sepFilter2D(image.contiguous().numpy(), -1, k, k, borderType=cv2.BORDER_REPLICATE)
        return torch.from_numpy(out).reshape(image.shape)
    return _shifted_blur(image, g.tolist())


def _host(t: Tensor) -> bool:
    """``t`` is a float32/64 CPU tensor outside autograd (OpenCV's fast paths apply)."""
    return t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) and not t.requires_grad


def _shifted_blur(image: Tensor, g: list[float]) -> Tensor:
    """:func:`gaussian_blur` with the kernel ``g`` (``2 r + 1`` taps) as weighted sums of shifted views in the image's
    own layout, any device, differentiable (``F.conv2d`` with one group per channel took several times as long on the
    CPU). ``# [H, W, C]``"""
    r = len(g) // 2
    H, W = image.shape[:2]
    rows = (torch.arange(-r, H + r, device=image.device)).clamp(0, H - 1)  # [H + 2r] replicated border
    cols = (torch.arange(-r, W + r, device=image.device)).clamp(0, W - 1)  # [W + 2r]
    img = image[:, cols]  # [H, W + 2r, C]
    out = img[:, :W] * g[0]  # [H, W, C] along rows
    for o in range(1, 2 * r + 1):
        out.add_(img[:, o:o + W], alpha=g[o])
    img = out[rows]  # [H + 2r, W, C]
    out = img[:H] * g[0]  # along columns
    for o in range(1, 2 * r + 1):
        out.add_(img[o:o + H], alpha=g[o])
    return out


def soften_edges(image: Tensor, depth: Tensor, sigma: float, bend: float = EDGE_BEND) -> Tensor:
    """``image # [H, W, C]`` with the pixels on :func:`depth_edges` of its z-depth ``depth # [H, W]`` (0: no
    surface) replaced by the image blurred by a Gaussian of ``sigma`` pixels (module docstring); ``sigma <= 0``:
    ``image``. ``# [H, W, C]``"""
    if sigma <= 0:
        return image
    edge = depth_edges(depth.to(image.device), bend)  # [H, W]
    if not bool(edge.any()):
        return image
    blurred = gaussian_blur(image, sigma)
    if _host(image) and blurred.is_contiguous():  # the image kept off the edges, in place in the fresh blur
        keep = np.repeat(~edge.numpy()[..., None], image.shape[-1], -1)  # [H, W, C] (a full mask: a faster copy)
        np.copyto(blurred.numpy(), image.numpy(), where=keep)
        return blurred
    return torch.where(edge[..., None], blurred, image)
