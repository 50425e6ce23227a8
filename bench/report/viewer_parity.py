"""BENCHMARKS.md section: the web viewer against the real-time mesh path (`python -m bench viewer_parity`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import table_section


def _setting(s: dict) -> str:
    per_frame = "every training view" if not s["sources"] else f"{s['sources']} sources per frame"
    angle = f", {s['angle_sources']} per point{', source masks' if s.get('source_masks') else ''}" \
        if s["blend"] == "angle" else ""
    cracks = f", cracks {s['cracks']}" if s.get("cracks") else ""
    return f"{s['blend']} ({per_frame}{angle}), {s['fill']} fill{cracks}"


def _line(row: dict) -> str:
    key = "_masked" if row.get("scored_by") == "objects" else ""
    b = row["bundle"]
    return (f"{row['scene']} ({len(row['held_out'])} views, {row['resolution'][0]}x{row['resolution'][1]}) | "
            f"{_setting(row['setting'])} | v{b['version']}, {b['sources']} sources, {b['megabytes']:g} MB | "
            f"{row['python' + key]:.2f} | {row['browser' + key]:.2f} | {row['parity']:.2f} | {row['max_diff']} / "
            f"{row['mean_diff']:.2f} | {row['browser_ms_per_frame']:.0f} | {row['python_cpu_ms_per_frame']:.0f} | "
            f"{row['load_average'][0]:.1f}")


def section(results: Path) -> str | None:
    return table_section(
        results, "viewer_parity.json", "The web viewer against the real-time mesh path (`python -m bench viewer_parity`)",
        "Held-out views drawn by the bundle `omnirecon export` writes (headless Chromium, software WebGL2, as the "
        "bundle starts) and by `MeshRenderer` with the real-time setting of the scene's finetune record "
        "(`realtime_setting`, with the crack fill), at the scene's resolution. PSNR against the photos (over the "
        "object masks where finetune scores them, DTU; the whole image elsewhere), the browser's PSNR against `MeshRenderer`'s frames (whole "
        "image) and the largest / mean absolute difference between them in 8-bit levels; the browser's wall "
        "milliseconds per frame (SwiftShader on the CPU) beside `MeshRenderer`'s CPU milliseconds (1 thread). "
        "Pictures: `bench/results/figures/viewer_parity_<scene>.png` (photo | MeshRenderer | browser | 4x difference).",
        ["scene", "setting", "bundle", "MeshRenderer dB", "browser dB", "browser vs MeshRenderer dB",
         "max / mean diff", "browser ms", "MeshRenderer CPU ms", "load"], _line)
