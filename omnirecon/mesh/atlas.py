"""A texel table for bilinear sampling of ``K`` maps at once (:class:`TexelAtlas`), what the mesh path's fused shader
(:mod:`omnirecon.mesh.shader`) samples the source colours and the projected appearance features from."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


class TexelAtlas:
    """``K`` channel-first maps ``# [K, C, h, w]`` as one row table for bilinear sampling with
    :func:`torch.nn.functional.embedding_bag` (a weighted sum of 4 rows per sample, one call for all
    ``K`` maps).

    ``padding="zeros"`` adds a one-texel border of ``pad_value # [C]`` (default 0) around each map:
    taps outside a map read it, as ``grid_sample(padding_mode="zeros")`` does for 0 (samples must lie
    inside the image or be masked out). ``"border"`` clamps texel coordinates to the map, as
    ``padding_mode="border"``. Both match ``grid_sample(..., align_corners=False)`` up to the float
    rounding of the coordinates. The bilinear weights of a sample sum to 1; masked samples read 0.
    """

    def __init__(self, maps: Tensor, padding: str = "zeros", pad_value: Tensor | None = None):
        if padding not in ("zeros", "border"):
            raise ValueError(f"padding must be 'zeros' or 'border', got {padding!r}")
        self.padding = padding
        """``"zeros"`` or ``"border"``."""
        self.K, self.C, self.h, self.w = maps.shape
        p = 1 if padding == "zeros" else 0
        if p and pad_value is not None:
            value = pad_value.to(maps).reshape(1, -1, 1, 1)
            maps = F.pad(maps - value, (p, p, p, p)) + value
        else:
            maps = F.pad(maps, (p, p, p, p))
        self._row_len = self.w + 2 * p
        self._zero_row = self.K * (self.h + 2 * p) * self._row_len
        rows = maps.permute(0, 2, 3, 1).reshape(-1, self.C)
        # zero tail: taps one past a map's last texel (weight 0), and masked samples, stay in the table
        self.rows = torch.cat([rows, rows.new_zeros(self._row_len + 2, self.C)]).contiguous()
        """The texels, map-major then row-major, then a zero tail. ``# [K (h + 2p) (w + 2p) + w + 2p + 2, C]``"""
        self._map_len = (self.h + 2 * p) * self._row_len
        self._pad = p
        self._index_dtype = torch.float32 if len(self.rows) < 2**24 else torch.float64  # exact integers
        self._scale = torch.tensor([self.w, self.h], dtype=self._index_dtype, device=maps.device)[None, :, None]
        self._hi = self._scale - 1  # largest texel-centre coordinate per axis (border mode)
        self._offsets = torch.tensor([0, 1, self._row_len, self._row_len + 1], device=maps.device)

    def taps(self, coords: Tensor, mask: Tensor | None = None, scale: Tensor | None = None,
             maps: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Rows and weights of the bilinear samples at image fractions ``coords # [K, 2, n]``
        (``u / W, v / H``; map ``k`` for row ``k``, or map ``maps[k, i]`` for sample ``(k, i)`` with
        ``maps # [K, n]`` int64). Samples where ``mask # [K, n]`` is False read 0.
        ``scale # [1, 2, 1]``: texels per unit of ``coords`` instead of the map size (e.g. ``(w / W, h / H)``
        for pixel coordinates). Returns ``index # [K n, 4]`` int64 and ``weight # [K n, 4]``, row-major in ``(k, i)``."""
        K, _, n = coords.shape
        xy = coords.to(self._index_dtype) * (self._scale if scale is None else scale)  # [K, 2, n]
        xy += self._pad - 0.5  # texel-centre coordinates in the padded map
        if self.padding == "border":
            xy.clamp_(min=0)
            xy = torch.minimum(xy, self._hi, out=xy)
        corner = xy.floor()
        frac = (xy - corner).to(coords.dtype)  # [K, 2, n]
        k = (torch.arange(K, device=xy.device)[:, None] if maps is None else maps).to(xy.dtype) * self._map_len
        base = torch.add(corner[:, 0], corner[:, 1], alpha=self._row_len).add_(k).long()  # [K, n]
        if mask is not None:
            base.masked_fill_(~mask, self._zero_row)
        index = base[..., None] + self._offsets  # [K, n, 4]
        rest = 1 - frac
        weight = torch.empty(K, n, 4, dtype=frac.dtype, device=frac.device)  # (y0 x0, y0 x1, y1 x0, y1 x1)
        fx, fy, gx, gy = frac[:, 0], frac[:, 1], rest[:, 0], rest[:, 1]
        torch.mul(gx, gy, out=weight[..., 0])  # strided writes: far faster than a broadcast outer product
        torch.mul(fx, gy, out=weight[..., 1])
        torch.mul(gx, fy, out=weight[..., 2])
        torch.mul(fx, fy, out=weight[..., 3])
        return index.reshape(-1, 4), weight.reshape(-1, 4)

    def sample(self, index: Tensor, weight: Tensor) -> Tensor:
        """Weighted sums of the tapped rows. ``# [K n, C]``"""
        return F.embedding_bag(index, self.rows, per_sample_weights=weight, mode="sum")

