"""BENCHMARKS.md section: `omnirecon mesh`'s default resolution, 128 px against the photos' size
(`python -m bench mesh_resolution`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import table_section


def _line(row: dict) -> str:
    w, h = row["mesh_resolution"]
    masked = f"{row['psnr_masked']:.2f}" if "psnr_masked" in row else "–"
    return (f"{row['scene']} | {w}x{h}{' (photos)' if row['mesh_side'] == row['photo_side'] else ''} | "
            f"{row['depth']} | {row['faces']:,} | {row['mesh_cpu_seconds']:.1f} | {row['psnr']:.2f} | {masked} | "
            f"{row['psnr_covered']:.2f} | {row['coverage']:.1%} | {row['load_average'][0]:.1f}")


def section(results: Path) -> str | None:
    return table_section(
        results, "mesh_resolution.json", "Mesh resolution (`python -m bench mesh_resolution`)",
        "`omnirecon mesh SCENE --ckpt checkpoints/omnirecon-tiny --views all --resolution S` (as `reconstruct` runs it, "
        "`--depth auto`), process CPU seconds at 1 thread from reading the images to the written mesh, scored before "
        "tuning like `omnirecon finetune --mesh M --nearest 6` at the photos' size (held-out views; over the object "
        "masks where the scene has them):",
        ["scene", "meshed at", "depth", "faces", "mesh CPU s", "whole image dB", "mask dB", "covered dB", "coverage",
         "load"], _line)
