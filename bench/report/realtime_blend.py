"""BENCHMARKS.md section: the real-time mesh path blending as finetune scored (`python -m bench realtime_blend`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import table_section


def _setting(s: dict) -> str:
    angle = f", {s['angle_sources']} per point{', source masks' if s.get('source_masks') else ''}" \
        if s["blend"] == "angle" else ""
    return f"{s['blend']} ({s['sources']} sources per frame{angle}), {s['fill']} fill"


def _line(row: dict) -> str:
    key = "psnr_masked" if "psnr_masked" in row["before"] else "psnr"
    b, f = row["before"], row["finetune"]
    return (f"{row['scene']} | {row['finetune_record'][key]:.2f} | {_setting(b['setting'])} | {b[key]:.2f} | "
            f"{b['cpu_ms_per_frame']:.0f} | {_setting(f['setting'])} | {f[key]:.2f} | {f['cpu_ms_per_frame']:.0f} | "
            f"{row['load_average'][0]:.1f}")


def section(results: Path) -> str | None:
    return table_section(
        results, "realtime_blend.json", "Real-time mesh path against finetune's scores (`python -m bench realtime_blend`)",
        "Finetune's held-out views rendered frame by frame by the real-time mesh renderer (`MeshRenderer`, the path "
        "videos and `render --mesh` take), each frame from its own nearest training views, with the setting the "
        "videos used before session 16 and with the one finetune records (`curve.json` \"render\"); beside it the "
        "finetune record's own score of the same views (before tuning). PSNR over the object masks on DTU, the "
        "whole image on fern; CPU ms per frame at 1 thread (median, ratios within a row compare).",
        ["scene", "finetune scored", "real-time before: setting", "dB", "CPU ms", "with finetune's setting", "dB",
         "CPU ms", "load"], _line)
