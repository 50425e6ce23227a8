"""The mesh path's fused shader: the blend of :mod:`omnirecon.mesh.kernel` at many surface points of one frame,
fast, over one set of source views (:class:`SourceShader`, the per-point half of
:class:`omnirecon.mesh.ibr.MeshRenderer`).

**Network blend, fused** (``MeshRenderOptions.fused``, the default): the same function as ``OmniRecon.shade`` with
less work per frame (tests: equal to float tolerance). Per scene, the appearance projection is applied to the feature
maps (``W F_i + b``; bilinear sampling is linear and its weights sum to 1, so sampling that map equals ``W f + b``; the
map's zero padding becomes a border of ``b``), and the ``K`` maps become one texel table
(:class:`omnirecon.mesh.atlas.TexelAtlas`) sampled with ``embedding_bag`` (a weighted sum of 4 rows: several times
faster than ``grid_sample`` for 16 channels on the CPU). Where fewer than two sources see a point its weights need no
network (one source: weight 1 exactly, as the softmax gives against the others' ``-1e9`` logits; none: ``1 / K``
each), so only the other points are compacted and shaded; every MLP layer is one matrix product over all ``K x n``
point-view pairs (layers 2 and 3 column-major: several times faster than row-major for these narrow layers), and the
source colours are sampled exactly as the model does.

**Angle blend**: :func:`omnirecon.mesh.kernel.lumigraph` over each point's ``angle_sources + 1`` sources nearest by
angle only (:meth:`SourceShader._angle_top`, ranked by cosine), times the mask falloff
(:func:`omnirecon.mesh.kernel.apply_mask_factor`); the colour samples only the sources a point weighs
(:meth:`SourceShader._sparse_rgb`). Equal to :func:`omnirecon.mesh.kernel.angle_blend_weights` over every source to
float rounding (``tests/mesh/test_mesh_render.py``, ``tests/mesh/test_kernel.py``).

**Signals.** The same weights render any per-view signal (``MeshRenderer.render_signal``): a ``[K, H', W', C]``
tensor (e.g. 2-D predictions to lift into 3-D), sampled like the source RGB (bilinear, border padding, at any
resolution covering the source images) and blended with ``omega``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from omnirecon.mesh.atlas import TexelAtlas
from omnirecon.mesh.kernel import (
    angle_blend_weights,
    apply_mask_factor,
    consensus_weights,
    lumigraph,
    mask_factor,
    norm3,
    unoccluded,
)
from omnirecon.render.raster import Surface


@dataclass
class ShadeResult:
    """Blend weights of the covered pixels of one frame (``P`` pixels, ``K`` sources)."""

    surface: Surface
    """The covered pixels, their surface points and depths (CPU)."""
    omega: Tensor
    """Blend weight of each source at each covered pixel (sums to 1 over sources). ``# [K, P]``"""
    mask: Tensor
    """Source ``k`` sees the point: in front, inside its image and (with the visibility test) not
    occluded. ``# [K, P]`` bool"""
    coords: Tensor | None
    """Projection of each point into each source as a fraction of the image size, ``(u / W, v / H)``
    (inside the image: ``[0, 1)``); what :meth:`MeshRenderer.blend` samples signals at (``None`` when
    only the colour was asked for). ``# [K, 2, P]``"""
    rgb: Tensor | None = None
    """Blended source colour, when the shader computed it on the way. ``# [P, 3]``"""
    covered: int | None = None
    """The first ``covered`` pixels lie on the mesh, the rest on the fill's background layer
    (``None``: every pixel is on the mesh)."""



def _pick(t: Tensor | None, i: Tensor) -> Tensor | None:
    """``t[i]``, or ``None`` for ``None``."""
    return None if t is None else t[i]


class SourceShader:
    """Blend weights and colours at surface points over one set of sources (module docstring). The state it reads is
    set by :meth:`_setup_sources` (per-source geometry, colour atlas, folded appearance branch) and by its subclass
    :class:`omnirecon.mesh.ibr.MeshRenderer` (``options``, ``num_views``, ``source_depth_max``, ``mask_falloff``)."""

    def _setup_sources(self, model, sources) -> None:
        """Per-source geometry and maps of ``sources`` (under ``torch.inference_mode``)."""
        cams = sources.cameras.to(device=self.device, dtype=self.dtype)
        self._centers = cams.centers.T[:, :, None].contiguous()  # [3, K, 1]
        self._centers_t = cams.centers.contiguous()  # [K, 3]
        self._center_sq = (cams.centers * cams.centers).sum(1, keepdim=True)  # [K, 1]
        self._proj = (cams.K @ cams.w2c[:, :3, :]).reshape(-1, 4)  # [3K, 4]: world -> (u z, v z, z)
        self._size = torch.tensor([cams.width, cams.height], dtype=self.dtype, device=self.device)[None, :, None]
        self._two_over_size = 2 / self._size  # pixel coordinates -> grid_sample's [-1, 1]
        self._minus_one = torch.tensor(-1.0, dtype=self.dtype, device=self.device)
        self._images = sources.images.permute(0, 3, 1, 2)  # [K, 3, H, W]
        self._rgb = TexelAtlas(self._images, "border")
        self._one = torch.ones(1, 2, 1, dtype=self.dtype, device=self.device)  # taps at pixel coordinates
        if self.options.fused:
            self._feat, self._mlp = self._fold(model.appearance)
            self._uv_to_texel = self._feat._scale / self._size  # source pixels -> feature texels
        self._source_ids: Tensor | None = None  # a _subset's sources among the maps' (None: all, in order)
        self._parent = None  # a _subset's shader over every source

    def _fold(self, app) -> tuple[TexelAtlas, list[Tensor]]:
        """The appearance branch prepared for the fused shader (module docstring): the texel table of ``W F_i + b``
        (border ``b``) and the MLP: ``W1`` split into its feature and direction columns
        and transposed (``[C, h1]``, ``[3, h1]``), ``b1 # [h1]``, then ``W2``, ``b2``, ``W3``, ``b3`` as
        ``[out, in]`` matrices and ``[out, 1]`` biases."""
        dt = self.dtype
        W, b = app.proj.weight.to(dt), app.proj.bias.to(dt)  # [C, C], [C]
        maps = torch.einsum("dc,kchw->kdhw", W, self.features.maps) + b[:, None, None]  # [K, C, h, w]
        (w1, b1), (w2, b2), (w3, b3) = [(m.weight.to(dt), m.bias.to(dt)[:, None]) for m in app.mlp
                                        if isinstance(m, torch.nn.Linear)]
        C = W.shape[0]
        # layer 1 row-major ([K n, C] @ [C, h1]), the narrower layers 2 and 3 column-major
        mlp = [t.contiguous() for t in (w1[:, :C].T, w1[:, C:].T, b1[:, 0], w2, b2, w3, b3)]
        return TexelAtlas(maps, "zeros", pad_value=b), mlp

    def project(self, points: Tensor, layer: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Project ``points # [3, n]`` (channel-first) into every source: pixel coordinates
        ``uv # [K, 2, n]``, camera z-depth ``z # [K, n]`` and ``mask # [K, n]`` (in front, inside the
        image and, with the visibility test on, not occluded; points where ``layer # [n]`` bool is True, the fill's
        background layer, skip the occlusion test, as ``finetune`` scores them)."""
        uv, z, mask = self._frame_points(points)
        if self.source_depth_max is not None:
            vis = self.visible(uv, z)
            mask &= vis if layer is None else vis | layer  # the fill's far layer: every source that frames it
        return uv, z, mask

    def _frame_points(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """:meth:`project` without the occlusion test: ``uv # [K, 2, n]``, ``z # [K, n]`` and in front and inside the
        image ``# [K, n]``."""
        K = self.num_views
        uvz = torch.addmm(self._proj[:, 3:], self._proj[:, :3], points).reshape(K, 3, -1)  # [K, 3, n]
        z = uvz[:, 2]
        uv = uvz[:, :2] / z.clamp_min(1e-6)[:, None]  # as Cameras.project in front (behind: another point far outside)
        inside = (uv >= 0) & (uv < self._size)  # [K, 2, n]
        return uv, z, (z > 1e-6) & inside[:, 0] & inside[:, 1]  # (faster than .all(1) over the size-2 axis)

    def visible(self, uv: Tensor, z: Tensor) -> Tensor:
        """Occlusion test (module docstring) of points at source pixel coordinates ``uv # [K, 2, n]``
        with source z-depths ``z # [K, n]``. ``# [K, n]`` bool"""
        if self.source_depth_max is None:
            raise ValueError("the occlusion test needs MeshRenderOptions(visibility=True)")
        return unoccluded(self.source_depth_max, uv, z, self.options.visibility_tol, self._all_ids(uv.shape[2]))


    def _plain_points(self, points: Tensor, origin: Tensor, layer: Tensor | None, on_mesh: Tensor | None,
                      with_rgb: bool) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
        """The reference path (``fused=False``) at points ``# [P, 3]`` seen from ``origin # [3]``: the kernel's
        weights over every source (:func:`omnirecon.mesh.kernel.angle_blend_weights`, or ``model.shade``'s network
        weights) and their ``mask``: ``omega # [K, P]``, ``mask # [K, P]``, image fractions ``# [K, 2, P]`` and the
        network's colour ``# [P, 3]`` when ``with_rgb`` (the angle blend's: ``None``, sampled by the caller).
        ``layer``, ``on_mesh`` ``# [P]`` bool as :meth:`_shade_points`."""
        uv, _, mask = self.project(points.T, layer)
        if self.options.blend == "angle":
            omega = angle_blend_weights(points, origin, self.sources.cameras.centers.to(points), mask.T,
                                        self.options.angle_sources or self.num_views,
                                        None if self.mask_falloff is None else self._mask_factor(uv, on_mesh).T).T
            if self.options.consensus > 0:
                colours = self._rgb.sample(*self._rgb.taps(uv / self._size)).reshape(self.num_views, -1, 3)
                omega = consensus_weights(colours.transpose(0, 1), omega.T, self.options.consensus).T
            return omega, mask, uv / self._size, None
        out = self.model.shade(self.features, points, origin.expand_as(points),
                               visible=mask.T if self.options.visibility else None)
        return out["blend"].T, mask, uv / self._size, out["rgb"] if with_rgb else None

    def _shade_points(self, p: Tensor, d_t: Tensor, with_rgb: bool, with_coords: bool = False,
                      layer: Tensor | None = None, on_mesh: Tensor | None = None,
                      with_mask: bool = True) -> tuple[Tensor | None, Tensor | None, Tensor | None, Tensor | None]:
        """``OmniRecon.shade``, fused (module docstring), at points ``p # [3, n]`` (channel-first) seen along
        ``d_t # [3, n]`` (target -> point, any positive length): blend weights ``omega # [K, n]``, the
        mask ``# [K, n]``, with ``with_coords`` the source image fractions ``# [K, 2, n]`` and, with
        ``with_rgb``, the blended source colour ``# [3, n]``. ``layer # [n]`` bool: points on the fill's far layer (no
        occlusion test); ``on_mesh # [n]`` bool: points on the mesh (the only ones the source masks weigh; ``None``:
        all). Without ``with_mask`` (and with the angle blend, no ``with_coords`` nor consensus), only the colour:
        ``(None, None, None, rgb)``."""
        K = self.num_views
        angle = self.options.blend == "angle"
        if angle and not (with_mask or with_coords or self.options.consensus > 0):  # the frame path
            uv, z, framed = self._frame_points(p)
            top = self._angle_top(p, d_t, uv, z, framed, False, layer, on_mesh)
            wide = top[2]
            if self._parent is None or not len(wide) or not with_rgb:
                return None, None, None, self._sparse_rgb(*top, uv) if with_rgb else None
            rgb = self._sparse_rgb(*top[:2], wide[:0], top[3][:, :0], uv)  # points no candidate weighs: every source
            rgb[:, wide] = self._parent._shade_points(p[:, wide], d_t[:, wide], True, layer=_pick(layer, wide),
                                                      on_mesh=_pick(on_mesh, wide), with_mask=False)[3]
            return None, None, None, rgb
        uv, z, mask = self.project(p, layer)  # [K, 2, n], [K, n]
        st = uv / self._size if with_coords else None  # [K, 2, n] image fractions
        seen = mask.sum(0)  # [n] sources that see each point
        few = seen < 2
        n_few = int(few.sum())
        top = None
        if angle:
            top = self._angle_top(p, d_t, uv, z, mask, True, layer, on_mesh)
            om = self._dense(*top)
        elif n_few == 0:
            om = self._blend_logits(p, d_t, uv, mask)
        else:  # omega needs no network where fewer than 2 sources see the point (module docstring)
            om = torch.where(seen == 0, 1.0 / K, mask.to(self.dtype))  # [K, n]
            if n_few < p.shape[1]:
                if n_few * self.SKIP_BELOW < p.shape[1]:  # few such points: not worth the compaction
                    om = torch.where(few, om, self._blend_logits(p, d_t, uv, mask))
                else:
                    i = (~few).nonzero()[:, 0]
                    om[:, i] = self._blend_logits(p[:, i], d_t[:, i], uv[:, :, i], mask[:, i])
        rgb = None
        consensus = self.options.blend == "angle" and self.options.consensus > 0
        if with_rgb and top is not None and not consensus:
            return om, mask, st, self._sparse_rgb(*top, uv)
        if with_rgb or consensus:  # the model's own sampling of the source colours
            grid = torch.addcmul(self._minus_one, uv, self._two_over_size).transpose(1, 2)[:, None]  # [K, 1, n, 2]
            c = F.grid_sample(self._images, grid, align_corners=False, padding_mode="border")[:, :, 0]  # [K, 3, n]
            if consensus:
                om = consensus_weights(c.permute(2, 0, 1), om.T, self.options.consensus).T.contiguous()
        if with_rgb:
            rgb = c[0].mul_(om[0])  # [3, n]
            for k in range(1, K):
                rgb.addcmul_(c[k], om[k])
        return om, mask, st, rgb

    def _sparse_rgb(self, w: Tensor, idx: Tensor, wide: Tensor, wide_om: Tensor, uv: Tensor) -> Tensor:
        """The angle blend's colour ``# [3, n]`` from :meth:`_angle_top`, sampling only the weighted sources: one
        :class:`~omnirecon.mesh.atlas.TexelAtlas` tap set per (point, source) pair of ``idx``, summed with the weights by ``embedding_bag``
        (bilinear, border padding: ``grid_sample``'s colours up to the float rounding of the coordinates); the ``wide``
        points blend every source as :meth:`_shade_points` does."""
        k1, n = idx.shape
        sel = uv.gather(0, idx[:, None].expand(k1, 2, n))  # [k1, 2, n] source pixels
        index, weight = self._rgb.taps(sel, scale=self._one, maps=self._ids(idx))  # [k1 n, 4]
        weight = weight.reshape(k1, n, 4).mul_(w[..., None]).transpose(0, 1).reshape(n, 4 * k1)
        rgb = F.embedding_bag(index.reshape(k1, n, 4).transpose(0, 1).reshape(n, 4 * k1), self._rgb.rows,
                              per_sample_weights=weight, mode="sum").T  # [3, n]
        if len(wide):
            grid = torch.addcmul(self._minus_one, uv[:, :, wide], self._two_over_size).transpose(1, 2)[:, None]
            images = self._images if self._source_ids is None else self._images[self._source_ids]
            c = F.grid_sample(images, grid, align_corners=False, padding_mode="border")[:, :, 0]  # [K, 3, m]
            rgb[:, wide] = (c * wide_om[:, None]).sum(0)
        return rgb.contiguous()

    SKIP_BELOW = 8
    """:meth:`_shade_points` compacts the points at least two sources see when the others are at least
    ``1 / SKIP_BELOW`` of a chunk (below that, the gather costs more than the network it saves)."""

    def _mask_factor(self, uv: Tensor, on_mesh: Tensor | None) -> Tensor:
        """:func:`~omnirecon.mesh.kernel.mask_factor` at source pixels ``uv # [K, 2, n]``, 1 at the points not on the mesh (``on_mesh # [n]``
        bool False: the fill's points, off the object where the target sees no surface). ``# [K, n]``"""
        fac = mask_factor(self.mask_falloff, uv, self._all_ids(uv.shape[2]))
        return fac if on_mesh is None else torch.where(on_mesh, fac, torch.ones_like(fac))

    def _angle_top(self, p: Tensor, d_t: Tensor, uv: Tensor, z: Tensor, seen: Tensor, tested: bool,
                   layer: Tensor | None = None, on_mesh: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``blend="angle"``: :func:`~omnirecon.mesh.kernel.lumigraph_weights` at points ``p # [3, n]`` seen along ``d_t # [3, n]`` by the
        sources of ``seen # [K, n]`` (times :meth:`_mask_factor` at their pixels ``uv # [K, 2, n]`` when the sources
        carry masks; ``on_mesh # [n]``: which points lie on the mesh), for the ``k + 1`` sources nearest by angle only
        (``k`` = ``angle_sources``; the largest cosines, no arccos of the others). Unless ``tested``, ``seen`` is
        :meth:`_frame_points`' (no occlusion test) and the occlusion test (source z-depths ``z # [K, n]``; ``layer``
        as :meth:`project`) runs on the ``2 (k + 1)`` nearest only, and on every source for the points where fewer
        than ``k + 1`` of those pass and more sources frame them (the same sources as testing every one).

        Returns weights ``w # [k1, n]`` of sources ``idx # [k1, n]`` (``k1 = min(k + 1, K)``; the last weighs 0
        unless ``k1 = K``), the points no source weighs ``wide # [m]`` (every source at ``1 / K``, times the mask
        factor) and their weights ``# [K, m]``."""
        K, n = seen.shape
        k = max(1, min(self.options.angle_sources or K, K))
        k1 = min(k + 1, K)
        t = d_t / norm3(d_t)  # [3, n] unit target rays
        cos = self._cosines(p, t).masked_fill_(~seen, -2.0)  # sources that do not see the point: after every one that does
        if tested or self.source_depth_max is None:
            c, idx = cos.topk(k1, dim=0)  # [k1, n]: ascending angle
        else:
            m = min(2 * k1, K)
            c, idx = cos.topk(m, dim=0)  # [m, n] the candidates
            vis = unoccluded(self.source_depth_max, uv.gather(0, idx[:, None].expand(m, 2, n)), z.gather(0, idx),
                             self.options.visibility_tol, self._ids(idx))
            c = c.masked_fill(~(vis if layer is None else vis | layer), -2.0)
            c, j = c.topk(k1, dim=0)  # sorted again: the occluded ones last
            idx = idx.gather(0, j)
            short = ((c[-1] < -1.5) & (seen.sum(0) > m)).nonzero()[:, 0]  # visible sources may lie beyond
            if len(short):
                vis = self.visible(uv[:, :, short], z[:, short])
                c[:, short], idx[:, short] = cos[:, short].masked_fill(
                    ~(vis if layer is None else vis | layer[short]), -2.0).topk(k1, dim=0)
        d_s = p[:, None] - self._centers[:, :, 0].T.gather(0, idx.reshape(-1, 1).expand(-1, 3)).T.reshape(3, k1, n)
        exact = (t[:, None] * (d_s / norm3(d_s))).sum(0).clamp_(-1, 1)  # [k1, n] the chosen sources' cosines
        ang = torch.arccos(exact).masked_fill_(c < -1.5, float("inf"))  # [k1, n]
        thresh = ang[k:k + 1] if K > k else torch.full_like(ang[:1], float("inf"))  # [1, n]
        w = lumigraph(ang, ang[k - 1:k], thresh)  # [k1, n]
        total = w.sum(0, keepdim=True)  # [1, n]
        w = w / total.clamp_min(1e-12)
        if self.mask_falloff is not None:
            fac = mask_factor(self.mask_falloff, uv.gather(0, idx[:, None].expand(k1, 2, n)), self._ids(idx))  # [k1, n]
            if on_mesh is not None:
                fac = torch.where(on_mesh, fac, torch.ones_like(fac))
            w = apply_mask_factor(w, fac, dim=0)
        wide = (total[0] <= 0).nonzero()[:, 0]  # [m]
        wide_om = torch.full((K, len(wide)), 1.0 / K, dtype=w.dtype, device=w.device)
        if len(wide) and self.mask_falloff is not None:
            fac = self._mask_factor(uv[:, :, wide], None if on_mesh is None else on_mesh[wide])
            wide_om = apply_mask_factor(wide_om.T, fac.T).T
        return w, idx, wide, wide_om

    def _cosines(self, p: Tensor, t: Tensor) -> Tensor:
        """Cosine of the angle between each source's ray to points ``p # [3, n]`` and the unit target rays ``t # [3, n]``,
        ``t . (p - c) / |p - c|``, from two ``[K, 3] x [3, n]`` products (no ``[3, K, n]`` temporaries; the weights take
        the cosines of the chosen sources computed directly). ``# [K, n]``"""
        sq = torch.addmm(self._center_sq, self._centers_t, p, alpha=-2).add_((p * p).sum(0))  # [K, n] |p - c|^2
        return torch.addmm((t * p).sum(0)[None], self._centers_t, t, alpha=-1).mul_(sq.clamp_min_(1e-24).rsqrt_())

    def _frame_sources(self, depth: Tensor, size: tuple[int, int], origin: Tensor, rays, far_z):
        """``shader(sl)``: the renderer the frame's pixels ``sl`` (a slice of the row-major ``H W``) are shaded by
        (``options.frame_grid``): one over their candidate sources only (those the grid points within ``frame_grid``
        rows of theirs rank), or ``self`` (option off, not the angle blend, or more than half the sources candidates:
        lund's street, 25 sources, ran 360 -> 479 CPU-ms per frame with every subset).
        ``depth # [H W]`` (after the nearest fill; <= 0: none) of a frame of ``size = (H, W)`` seen from
        ``origin # [3]``; ``rays(pixels) # [3, g]``: the rays through pixels at camera z = 1; ``far_z(rays) # [g]``:
        the fill's far-layer depth (``None``: the background colour, no point)."""
        K, g = self.num_views, self.options.frame_grid
        k1 = min(max(1, self.options.angle_sources or K) + 1, K)
        H, W = size
        if self.options.blend != "angle" or g <= 0 or K <= 2 * k1:
            return lambda sl: self
        rows, cols = torch.arange(g // 2, H, g), torch.arange(g // 2, W, g)
        pix = (rows[:, None] * W + cols[None]).reshape(-1).to(self.device)  # [G] grid pixels
        z, d = depth[pix], rays(pix)  # [G], [3, G]
        if far_z is None:
            pix, z, d = pix[z > 0], z[z > 0], d[:, z > 0]
        else:
            z = torch.where(z > 0, z, far_z(d))
        p = d * z + origin[:, None]  # [3, G]
        framed = self._frame_points(p)[2]
        c, idx = self._cosines(p, d / norm3(d)).masked_fill_(~framed, -2.0).topk(min(2 * k1, K), dim=0)  # [2 k1, G]
        idx = idx.masked_fill_(c < -1.5, K)  # K: none

        def shader(sl: slice) -> SourceShader:
            near = (pix >= (sl.start // W - g) * W) & (pix < ((sl.stop - 1) // W + g + 1) * W)  # [G]
            cand = idx[:, near].unique()  # sorted source indices (K last)
            cand = cand[cand < K]
            return self if len(cand) == 0 or 2 * len(cand) > K else self._subset(cand)  # worth it below half

        return shader

    def _subset(self, cand: Tensor) -> SourceShader:
        """A shallow copy of this renderer over sources ``cand # [M]``: its per-source geometry indexed, its maps (colour
        atlas, occlusion depths, mask falloff) shared and read through :meth:`_ids`."""
        import copy

        sub = copy.copy(self)
        sub.num_views, sub._source_ids, sub._parent = len(cand), cand, self
        sub._centers, sub._centers_t = self._centers[:, cand].contiguous(), self._centers_t[cand].contiguous()
        sub._center_sq = self._center_sq[cand].contiguous()
        sub._proj = self._proj.reshape(-1, 3, 4)[cand].reshape(-1, 4).contiguous()  # [3M, 4]
        return sub

    def _ids(self, idx: Tensor) -> Tensor:
        """Source indices ``idx # [k, n]`` of this renderer as indices of its maps (a :meth:`_subset`'s differ)."""
        return idx if self._source_ids is None else self._source_ids[idx]

    def _all_ids(self, n: int) -> Tensor | None:
        """Every source's map index for ``n`` points (``None``: the identity). ``# [K, n]``"""
        return None if self._source_ids is None else self._source_ids[:, None].expand(-1, n)

    def _dense(self, w: Tensor, idx: Tensor, wide: Tensor, wide_om: Tensor) -> Tensor:
        """:meth:`_angle_top`'s weights over every source. ``# [K, n]``"""
        om = torch.zeros(self.num_views, w.shape[1], dtype=w.dtype, device=w.device).scatter_(0, idx, w)
        if len(wide):
            om[:, wide] = wide_om
        return om

    def _blend_logits(self, p: Tensor, d_t: Tensor, uv: Tensor, mask: Tensor) -> Tensor:
        """The appearance network's blend weights ``omega # [K, n]`` at points ``p # [3, n]`` seen along
        ``d_t # [3, n]``, projecting to source pixels ``uv # [K, 2, n]`` with ``mask # [K, n]``."""
        w1z, w1d, b1, w2, b2, w3, b3 = self._mlp
        K, n = self.num_views, p.shape[1]
        z = self._feat.sample(*self._feat.taps(uv, mask, self._uv_to_texel)).relu_()  # [K n, C]: ReLU(W f + b)
        d_s = p[:, None] - self._centers  # [3, K, n] sources -> point
        rel = (d_t / norm3(d_t))[:, None] - d_s / norm3(d_s)  # [3, K, n]
        hid = torch.addmm(b1, z, w1z).addmm_(rel.reshape(3, K * n).T, w1d).relu_()  # [K n, h1]
        hid = torch.addmm(b2, w2, hid.T).relu_()  # [h2, K n]
        logit = torch.addmm(b3, w3, hid).reshape(K, n).masked_fill_(~mask, -1e9)
        return torch.softmax(logit, dim=0)  # [K, n]

