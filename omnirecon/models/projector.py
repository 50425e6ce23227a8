"""The one projector every model uses: project 3-D points into the source views and bilinearly sample
per-view 2-D maps (features, colours, lifted signals) there, for all views at once.

``project(cameras, points # [..., 3])`` remembers the points' leading shape (``[R, S]``: rays and samples
along them); ``gather(maps, projection)`` returns the samples in that shape with the views and channels
last, ``# [R, S, V, C]``, and ``Projection.mask`` the in-image test as ``# [R, S, V]``.

Pixel centres sit at ``+0.5`` (docs/conventions.md), so a pixel coordinate ``u`` maps to the
``grid_sample`` coordinate ``2 u / W - 1`` with ``align_corners=False``. Sampling outside the image
reads zeros (``padding="zeros"``: features, whose absence the ``in_image`` mask also marks) or the
nearest border pixel (``padding="border"``: colours and signals, so that blends stay finite).
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from omnirecon.cameras import Cameras

Padding = Literal["zeros", "border"]
"""Where a sample falls outside a map: zeros, or the nearest border pixel."""


class Projection(NamedTuple):
    """Where points land in each of ``V`` views."""

    grid: Tensor
    """``grid_sample`` coordinates of each point in each view. ``# [V, 1, P, 2]``"""
    in_image: Tensor
    """The point lies in front of the camera and inside the image. ``# [V, P]`` bool"""
    shape: tuple[int, ...] = ()
    """Leading shape of the projected points (``P`` of them), e.g. ``(R, S)``; ``()``: ``(P,)``."""

    @property
    def mask(self) -> Tensor:
        """``in_image`` in the points' shape, views last. ``# [..., V]`` bool"""
        shape = self.shape or (self.in_image.shape[1],)
        return self.in_image.reshape(-1, *shape).permute(*range(1, len(shape) + 1), 0)


def image_grid(uv: Tensor, width: int, height: int) -> Tensor:
    """Pixel coordinates ``# [..., 2]`` -> ``grid_sample`` coordinates (``align_corners=False``)."""
    return uv / torch.tensor([width, height], dtype=uv.dtype, device=uv.device) * 2 - 1


def project(cameras: Cameras, points: Tensor, dtype: torch.dtype | None = None) -> Projection:
    """Project ``points # [..., 3]`` (world) into every camera of ``cameras`` (``V`` views of one size).

    ``dtype``: of the returned grid (default: the points'); the projection itself runs in the
    points' dtype."""
    proj = cameras.project(points.reshape(-1, 3))  # [V, P]
    grid = image_grid(proj.uv, cameras.width, cameras.height)
    return Projection(grid.to(dtype or points.dtype)[:, None], proj.in_image, tuple(points.shape[:-1]))


def sample(maps: Tensor, projection: Projection, padding: Padding = "zeros") -> Tensor:
    """Bilinear samples of per-view ``maps # [V, C, H, W]`` at a :class:`Projection`. ``# [V, C, P]``"""
    out = F.grid_sample(maps, projection.grid.to(maps.dtype), align_corners=False, padding_mode=padding)
    return out[:, :, 0]


def gather(maps: Tensor | list[Tensor], projection: Projection, padding: Padding | list[Padding] = "zeros") -> Tensor:
    """:func:`sample` laid out per point: per-view ``maps # [V, C, H, W]`` at the projected points of shape
    ``[R, S]`` (``projection.shape``), views and channels last. ``# [R, S, V, C]`` (a view of the samples).

    A list of maps (one ``padding`` each) gives their samples concatenated along the channels, in one
    buffer laid out as the single-map case (``# [R, S, V, C1 + C2 + ...]``)."""
    if isinstance(maps, Tensor):
        out = sample(maps, projection, padding)  # [V, C, P]
    else:
        pads = [padding] * len(maps) if isinstance(padding, str) else padding
        out = torch.cat([sample(m, projection, p) for m, p in zip(maps, pads)], 1)  # [V, C1 + C2 + ..., P]
    shape = projection.shape or (out.shape[-1],)
    return out.reshape(*out.shape[:2], *shape).permute(*range(2, len(shape) + 2), 0, 1)
