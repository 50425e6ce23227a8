"""BENCHMARKS.md from the results JSON in ``bench/results/``: one module per section, registered in SECTIONS.

Each section module has ``section(results: Path) -> str | None`` (None: leave the section out) and reads only
the JSON the measuring modules wrote. A new benchmark adds its measuring module (``bench/<name>.py``), a section
module here and one entry below.
"""

from __future__ import annotations

from pathlib import Path

from bench.report import (
    ablation,
    depth_sources,
    encoder_lever,
    end_to_end,
    extrapolation,
    finetune_curves,
    finetune_levers,
    finetune_surface,
    finetune_validation,
    geometry,
    geometry_budget,
    guided,
    hostile,
    levers,
    lift,
    mesh_lod,
    mesh_path,
    mesh_resolution,
    peer,
    poses,
    quality,
    realtime_blend,
    reliability,
    speed,
    synth,
    throughput,
    train_256,
    train_background,
    train_gpnr_levers,
    train_levers,
    train_views,
    training,
    viewer_parity,
)

# The page, in order.
SECTIONS = (synth, throughput, ablation, poses, reliability, encoder_lever, train_levers, train_background, train_gpnr_levers,
            train_256, train_views,
            extrapolation,
            depth_sources,
            realtime_blend, mesh_lod, viewer_parity, mesh_resolution, finetune_curves, finetune_levers, finetune_surface,
            finetune_validation, hostile,
            speed, guided, peer, levers, end_to_end, training, quality, geometry,
            mesh_path, geometry_budget, lift)

HEADER = ("# Benchmarks\n\n"
          "Every number below is produced by `python -m bench page` (which runs the benchmarks in `bench/`) from "
          "the JSON results in `bench/results/`; each table carries the provenance of the run that measured it, and "
          "a section measured with another checkpoint (weights or model config) than the shipped one is marked "
          "**Stale**. Numbers are what we measured, including where they fall short of a goal.\n")


def write_page(results: Path, out: Path) -> str:
    """Render every registered section from ``results`` and write the page to ``out`` (atomically)."""
    from omnirecon.data.io import atomic_path

    parts = [HEADER]
    for module in SECTIONS:
        text = module.section(results)
        if text:
            parts += [text, ""]
    text = "\n".join(parts)
    with atomic_path(out) as tmp:
        tmp.write_text(text)
    return text
