"""The most any tuning of the mesh path's blend can give on a scene: the held-out PSNR of the best blend of
the source colours, chosen per pixel with the ground truth in hand.

    python -m bench finetune_ceiling --scene fern=../shared/data/llff/fern --mesh fern=MESH.ply

The mesh path colours a pixel ``sum_k omega_k c_k``: a convex blend (``omega`` on the simplex, over the
sources that see the point; uniform when none does) of the ``K`` source colours sampled where the surface
point projects. Tuning the 2-D encoder and the appearance branch only changes ``omega``. So with the mesh
and the sources fixed, no tuning can beat, on any pixel, the blend that minimises the squared error to
the true colour; this script solves that per pixel (projected gradient on the simplex) on the same
held-out views, sources, resolution and fill as ``omnirecon finetune`` (PSNR per view over a fixed random
subset of ``PIXELS`` pixels of the image and of the object mask, averaged over views) and reports it beside
the pretrained model's on the same pixels: the gap is the ceiling of every tuning lever that changes blend weights. (Per-source
exposure scales the colours and can exceed it slightly; ``exposure`` rows of ``python -m bench finetune_levers`` measure it.)
With ``finetune``'s defaults (each pixel's ``--nearest 6`` sources among every training view, the visibility test;
``--no-visibility`` to drop the test, ``--nearest 0 --num-views 3`` for 3 fixed sources) the model blends, and the
ceiling chooses among, only the nearest sources that see each point, as ``finetune`` does; ``ceiling_all`` is the best
blend over every source the point projects into (occluded and farther ones too): what those limits give up.
Results merge into ``bench/results/finetune_ceiling.json``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
PIXELS = 16384
"""Pixels scored per held-out view (a fixed random subset of the image, and one of the object mask)."""


def project_simplex(w: torch.Tensor, allowed: torch.Tensor) -> torch.Tensor:
    """Euclidean projection of each row of ``w # [P, K]`` onto the simplex over its ``allowed # [P, K]`` entries
    (the others become 0). ``# [P, K]``"""
    big = torch.where(allowed, w, torch.full_like(w, -1e9))
    u, _ = big.sort(-1, descending=True)
    css = u.cumsum(-1) - 1
    k = torch.arange(1, w.shape[1] + 1, dtype=w.dtype)
    ok = (u - css / k > 0) & (u > -1e8)
    rho = ok.float().cumsum(-1).argmax(-1, keepdim=True)  # last index where ok holds
    theta = css.gather(-1, rho) / (rho + 1).to(w.dtype)
    return torch.where(allowed, (w - theta).clamp_min(0), torch.zeros_like(w))


def best_blend(colours: torch.Tensor, allowed: torch.Tensor, target: torch.Tensor, iters: int = 300) -> torch.Tensor:
    """Per pixel, the convex blend of ``colours # [P, K, 3]`` over ``allowed # [P, K]`` closest to ``target # [P, 3]``
    (rows with nothing allowed: the uniform blend, as the model). ``# [P, 3]``"""
    none = ~allowed.any(-1)
    allowed = allowed | none[:, None]
    w = allowed.float() / allowed.float().sum(-1, keepdim=True)  # [P, K]
    lip = (colours.square().sum((-1, -2)) + 1e-6)[:, None]  # a Lipschitz bound of the gradient per pixel
    for _ in range(iters):
        r = (w[..., None] * colours).sum(1) - target  # [P, 3]
        grad = (colours * r[:, None]).sum(-1)  # [P, K]
        w = project_simplex(w - grad / lip, allowed)
    w = torch.where(none[:, None], torch.full_like(w, 1 / w.shape[1]), w)
    return (w[..., None] * colours).sum(1)


@torch.no_grad()
def ceiling(path: Path, mesh_file: Path, resolution: int | None = None, nearest: int = 6, num_views: int = 3,
            max_held_out: int = 4, visibility: bool = True) -> dict:
    from omnirecon.mesh.pixels import encode_maps, visible_at
    from omnirecon.workflows.finetune import FinetuneConfig, prepare

    cfg = FinetuneConfig(ckpt=ROOT / "checkpoints" / "omnirecon-tiny", scene=path, mesh=mesh_file, resolution=resolution,
                         nearest=nearest, num_views=num_views, max_held_out=max_held_out, visibility=visibility)
    s = prepare(cfg)  # finetune's sources, held-out views, resolution, fill and per-pixel blend sets
    model, scene, held, background, views, targets = s.model, s.scene, s.held_px, s.background, s.views, s.targets
    model.eval()
    sources = s.sources
    feats = encode_maps(model, sources)
    g = torch.Generator().manual_seed(0)
    limited = any(v.visible is not None for v in held)  # the visibility test and/or --nearest limit the blend
    names = ("model", "ceiling", "ceiling_all") if limited else ("model", "ceiling")
    scores = {name: {"psnr": [], "psnr_masked": []} for name in names}
    for v in held:
        gt = scene.images[v.index].reshape(-1, 3).float()
        where = torch.full((len(gt),), -1, dtype=torch.long)
        where[v.pixels] = torch.arange(len(v.pixels))  # image pixel -> shaded pixel (-1: background colour)
        sets = {"psnr": torch.randperm(len(gt), generator=g)[:PIXELS]}
        if scene.masks is not None:
            inside = scene.masks[v.index].reshape(-1).bool().nonzero()[:, 0]
            sets["psnr_masked"] = inside[torch.randperm(len(inside), generator=g)[:PIXELS]]
        for key, pix in sets.items():
            shaded = where[pix] >= 0
            sub = where[pix][shaded]
            seen = model.gather(feats, v.points[sub][:, None], v.origin.expand(len(sub), 3))
            vis = visible_at(v, sub)  # [n, K] the occlusion test (None without it)
            allowed = seen.mask[:, 0] if vis is None else seen.mask[:, 0] & vis
            colours = {"model": model.shade(feats, v.points[sub], v.origin.expand(len(sub), 3), vis)["rgb"].clamp(0, 1),
                       "ceiling": best_blend(seen.rgb[:, 0].float(), allowed, v.target[sub])}
            if vis is not None:
                colours["ceiling_all"] = best_blend(seen.rgb[:, 0].float(), seen.mask[:, 0], v.target[sub])
            for name, rgb in colours.items():
                img = torch.tensor(background, dtype=torch.float32).expand(len(pix), 3).clone()
                img[shaded] = rgb.float()
                scores[name][key].append(float(-10 * torch.log10((img - gt[pix]).square().mean().clamp_min(1e-10))))
    out = {"scene": str(path), "mesh": str(mesh_file), "sources": views, "nearest": nearest, "held_out": targets,
           "resolution": [scene.width, scene.height], "pixels_per_view": PIXELS, "load_average": os.getloadavg()[0],
           "visibility": visibility}
    for name in names:
        out[name] = {k: float(np.mean(x)) for k, x in scores[name].items() if x}
    return out


def main(argv: list[str] | None = None) -> dict:
    from bench.finetune_levers import merge, scene_parser, scenes_and_meshes
    from omnirecon.provenance import provenance

    p = scene_parser(__doc__)
    p.add_argument("--nearest", type=int, default=6, help="each pixel's nearest sources (as omnirecon finetune --nearest)")
    p.add_argument("--num-views", type=int, default=3, help="sources K with --nearest 0 (as omnirecon finetune)")
    p.add_argument("--no-visibility", dest="visibility", action="store_false",
                   help="blend every source the point projects into (finetune --no-visibility)")
    a = p.parse_args(argv)
    result = {}
    for name, path, mesh in scenes_and_meshes(a):
        started = provenance(seed=0)
        row = ceiling(path, mesh, nearest=a.nearest, num_views=a.num_views, visibility=a.visibility)
        print(name, row["model"], "->", row["ceiling"])
        result = merge(a.out / "finetune_ceiling.json", name, row, started)
    return result
