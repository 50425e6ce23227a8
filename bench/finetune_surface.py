"""Tuning the surface itself (``finetune --tune surface``) against the default levers: held-out PSNR after 0, 10, 30
and 60 CPU-seconds, on the demo's procedural scene and on real captures (issue 43, Deliver item 2).

    python -m bench finetune_surface --scene demo=outputs/bench/finetune_surface/demo_128/scene_900999 \\
        --mesh demo=outputs/bench/finetune_surface/demo_stereo.ply --rows default surface

Rows (``ROWS``): ``default``, ``finetune``'s defaults (the 2-D encoder and the appearance branch; nothing under the
angle blend, which real object captures such as fox get); ``surface``, the mesh's per-vertex offsets along its normals
alone (:class:`omnirecon.mesh.offsets.SurfaceOffsets`; ``_grid32``: a 32-cube grid of offsets sampled at the vertices;
``_every50``: the tuning views rasterized again on the moved mesh every 50 steps); ``+default``, with the default
levers. Every row is ``omnirecon finetune``
with the same mesh, sources, validation and held-out views (4 at most), ``--clock cpu --threads 1``, the returned state
the best on validation (the start a candidate). A surface row also scores its returned moved mesh rasterized afresh
(``after_rerasterized``: what the real-time renderer would draw; the curve's scores keep each pixel's start face). Each
row records the 1-minute load average at its start and end and merges into ``bench/results/finetune_surface.json``.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import torch

from bench.finetune_levers import merge, scene_parser, scenes_and_meshes

ROOT = Path(__file__).resolve().parents[1]
ROWS = {
    "default": {},
    "surface": {"tune": ("surface",)},
    "surface_grid32": {"tune": ("surface",), "surface_res": 32},
    "surface_grid32_every50": {"tune": ("surface",), "surface_res": 32, "surface_every": 50},
    "surface_grid32+default": {"tune": ("encoder", "appearance", "surface"), "surface_res": 32},
}
"""Rows: overrides of :class:`~omnirecon.workflows.finetune.FinetuneConfig`."""
TIMES = (0.0, 10.0, 30.0, 60.0)
KEEP = ("seconds", "steps", "psnr", "psnr_masked", "psnr_covered", "coverage", "val_psnr", "val_psnr_now",
        "returned_from")


def rerasterized(cfg, work: Path) -> dict | None:
    """Held-out scores of the returned moved mesh (``<work>/mesh.ply``) rasterized afresh (no offsets)."""
    from omnirecon.engine.tuning import Tuner
    from omnirecon.workflows.finetune import prepare

    if not (work / "mesh.ply").is_file():
        return None
    moved = replace(cfg, mesh=work / "mesh.ply", tune=("surface",), save=False)
    s = prepare(moved)
    r = Tuner(moved, s, torch.Generator().manual_seed(0)).test_scores()
    return {k: r[k] for k in ("psnr", "psnr_masked", "psnr_covered", "coverage") if k in r}


def run_row(scene: str, path: Path, mesh: Path, row: str, seconds: float, threads: int,
            resolution: int | None) -> dict:
    from omnirecon.workflows.finetune import FinetuneConfig, run_finetune

    load0 = os.getloadavg()[0]
    work = ROOT / "outputs" / "bench" / "finetune_surface" / f"{scene}_{row}"
    cfg = FinetuneConfig(ckpt=ROOT / "checkpoints" / "omnirecon-tiny", scene=path, mesh=mesh, seconds=seconds,
                         eval_at=tuple(t for t in TIMES if t <= seconds), clock="cpu", threads=threads, out=work,
                         max_held_out=4, resolution=resolution, save="surface" in ROWS[row].get("tune", ()),
                         **ROWS[row])
    ft = run_finetune(cfg)
    first, last = ft["curve"][0], ft["curve"][-1]
    return {"scene": str(path), "mesh": str(mesh), "row": row,
            "settings": {k: list(v) if isinstance(v, tuple) else v for k, v in ROWS[row].items()},
            "tuned": ft["tuned"], "blend": ft["blend"], "fill": ft["fill"], "resolution": ft["resolution"],
            "faces": ft["faces"], "sources": ft["sources"], "validation_views": ft["validation_views"],
            "held_out": ft["held_out"], "returned_from": ft["returned_from"], "steps": last["steps"],
            "curve": [{k: c[k] for k in KEEP if k in c} for c in ft["curve"]],
            "before": {k: first[k] for k in KEEP if k in first}, "after": {k: last[k] for k in KEEP if k in last},
            "gain_db": last["psnr"] - first["psnr"], "surface": ft.get("surface"),
            "after_rerasterized": rerasterized(cfg, work) if "surface" in ft["tuned"] else None,
            "cpu_seconds": ft["cpu_seconds"], "load_average": {"start": load0, "end": os.getloadavg()[0]}}


def main(argv: list[str] | None = None) -> dict:
    from omnirecon.provenance import provenance

    p = scene_parser(__doc__)
    p.add_argument("--mesh-note", default="", help="how the meshes were made (recorded)")
    p.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--resolution", type=int, default=None, help="long side in pixels (default: finetune's)")
    a = p.parse_args(argv)
    result = {}
    for name, path, mesh in scenes_and_meshes(a):
        for row in a.rows:
            started = provenance(seed=0)
            r = run_row(name, path, mesh, row, a.seconds, a.threads, a.resolution)
            r["mesh_note"] = a.mesh_note
            print(name, row, " ".join(f"{c['seconds']:.0f}s {c['psnr']:.2f}" for c in r["curve"]),
                  f"rerasterized {r['after_rerasterized']}", f"load {r['load_average']}")
            result = merge(a.out / "finetune_surface.json", f"{name}/{row}", r, started)
    return result


if __name__ == "__main__":
    main()
