"""Where the DTU mask error is: the mesh path's held-out error over the object masks, split by what each pixel lies on.

    python -m bench dtu_split --mesh outputs/bench/depth_sources/dtu_scan24_stereo_fill/mesh.ply --scene dtu_scan24
    python -m bench dtu_split --mesh M --scene dtu_scan37 --sets fixed mesh4 nearest4 --stereo-mesh S

Scores a ``depth_sources`` mesh before tuning, as ``omnirecon finetune`` does (omnirecon-tiny, the occlusion test,
the far layer where the mesh misses, held-out views 0 13 35 48 at 400x300), with several source sets per held-out
view: ``fixed``: DTU's 23 24 33 for every view (``finetune``'s default); ``meshK``: the K views of the 14 meshing
views nearest the held-out view; ``nearestK``: the K nearest of all 41 training views; ``allmesh``: the 14 meshing
views. Each source set is encoded on its own (the encoder's batch statistics are over that set). Per set: mean
PSNR over the masks and the whole image, and the share of the mask pixels and of their squared error on the
stereo surface / on completion's fill faces (``--stereo-mesh``: the same scene's mesh without completion) / on the
far layer (no face), and by how many of the sources the occlusion test lets blend the point (0, 1, 2, 3+).
Writes ``bench/results/dtu_split_<scene>.json``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from omnirecon.data.io import write_json


def source_sets(scene, proto, targets, mesh_views, pool, names):
    """``{name: fn(target) -> source views}`` for the set names (module docstring)."""
    from omnirecon.engine.views import select_sources

    def near(candidates, k):
        return lambda t: select_sources(scene, scene.cameras[t], list(candidates), k)

    out = {}
    for n in names:
        if n == "fixed":
            out[n] = lambda t: [23, 24, 33]
        elif n == "allmesh":
            out[n] = lambda t: list(mesh_views)
        elif n.startswith("mesh"):
            out[n] = near(mesh_views, int(n[4:]))
        elif n.startswith("nearest"):
            out[n] = near(pool, int(n[7:]))
        else:
            raise SystemExit(f"error: unknown source set {n!r} (fixed, allmesh, meshK, nearestK)")
    return out


def split_view(model, scene, mesh, t, srcs, stereo) -> tuple[dict, float, float]:
    """Per-category ``[pixels, squared error]`` over view ``t``'s mask, its mask PSNR and whole-image PSNR."""
    from omnirecon.mesh.pixels import encode_maps, full_image, rasterize_views, render_pixels
    from omnirecon.rays import Sources

    (v,) = rasterize_views(mesh, scene, [t], True, srcs)
    with torch.no_grad():
        rgb = render_pixels(model, encode_maps(model, Sources.from_scene(scene, srcs)), v)
    img, gt = full_image(scene, v, rgb), scene.images[t].float()
    m = scene.masks[t].bool().reshape(-1)
    se = (img - gt).square().mean(-1).reshape(-1)  # [H*W]
    covered = torch.zeros_like(m)
    covered[v.pixels[:v.covered]] = True
    nvis = torch.full(m.shape, -1)
    nvis[v.pixels[:v.covered]] = v.visible[:v.covered].sum(-1)
    st = torch.from_numpy(stereo(scene.cameras[t]).reshape(-1) > 0) if stereo is not None else covered
    cats = {"stereo surface": covered & st, "fill faces": covered & ~st, "far layer": ~covered,
            "seen by 0": nvis == 0, "seen by 1": nvis == 1, "seen by 2": nvis == 2, "seen by 3+": nvis >= 3}
    out = {k: [int((c & m).sum()), float(se[c & m].sum())] for k, c in cats.items()}
    return out, float(-10 * torch.log10(se[m].mean())), float(-10 * torch.log10(se.mean()))


def main(argv: list[str] | None = None) -> dict:
    from bench.depth_sources import ROOT, held_out, load
    from omnirecon.engine.checkpoint import load_checkpoint
    from omnirecon.engine.protocols import targets_and_pool
    from omnirecon.mesh.complete import DepthRenderer
    from omnirecon.mesh.files import read_mesh
    from omnirecon.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", choices=("dtu_scan24", "dtu_scan37"), required=True)
    p.add_argument("--mesh", type=Path, required=True, help="a depth_sources mesh of that scene")
    p.add_argument("--stereo-mesh", type=Path, default=None, help="the same scene's mesh without completion")
    p.add_argument("--sets", nargs="+", default=["fixed", "allmesh", "mesh3", "mesh4", "nearest3", "nearest4"])
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    _, scene, proto, _ = load(a.scene, False)
    targets, mesh_views = held_out(scene, proto)
    _, pool = targets_and_pool(proto, scene)
    model, _ = load_checkpoint(ROOT / "checkpoints" / "omnirecon-tiny")
    model.eval()
    mesh = read_mesh(a.mesh, scene.to_input)
    stereo = DepthRenderer(read_mesh(a.stereo_mesh, scene.to_input)) if a.stereo_mesh else None
    result = {"provenance": provenance(seed=0), "scene": a.scene, "mesh": str(a.mesh),
              "stereo_mesh": str(a.stereo_mesh) if a.stereo_mesh else None, "held_out": targets, "sets": {}}
    for name, pick in source_sets(scene, proto, targets, mesh_views, pool, a.sets).items():
        t0 = time.process_time()
        total, masked, whole, used = {}, [], [], {}
        for t in targets:
            srcs = pick(t)
            cats, pm, pw = split_view(model, scene, mesh, t, srcs, stereo)
            for k, (n, s) in cats.items():
                total.setdefault(k, [0, 0.0])
                total[k][0] += n
                total[k][1] += s
            masked.append(pm)
            whole.append(pw)
            used[t] = srcs
        n_all = sum(total[k][0] for k in ("stereo surface", "fill faces", "far layer"))
        se_all = sum(total[k][1] for k in ("stereo surface", "fill faces", "far layer"))
        split = {k: {"pixel_share": n / n_all, "error_share": s / se_all, "psnr": float(-10 * np.log10(s / n))}
                 for k, (n, s) in total.items() if n}
        result["sets"][name] = {"psnr_masked": float(np.mean(masked)), "psnr": float(np.mean(whole)),
                                "per_view_masked": masked, "sources": used, "split": split,
                                "cpu_seconds": time.process_time() - t0}
        print(f"{a.scene} {name}: mask {np.mean(masked):.2f} dB, whole {np.mean(whole):.2f} dB; "
              + ", ".join(f"{k} {v['pixel_share']:.1%} px / {v['error_share']:.1%} err" for k, v in split.items()),
              flush=True)
    if stereo is not None:
        stereo.close()
    write_json(a.out / f"dtu_split_{a.scene}.json", result)
    return result
