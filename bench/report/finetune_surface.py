"""BENCHMARKS.md section: Tuning the surface (`python -m bench finetune_surface`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import prov, read
from bench.report.finetune_levers import commit

LABELS = {"default": "finetune's default levers (encoder + appearance; under the angle blend nothing)",
          "surface": "`--tune surface`: an offset per vertex along its normal",
          "surface_grid32": "`--tune surface --surface-res 32`: offsets from a 32³ grid sampled at the vertices",
          "surface_grid32_every50": "the same, tuning views rasterized again every 50 steps (`--surface-every 50`)",
          "surface_grid32+default": "`--tune encoder appearance surface --surface-res 32`"}


def cell(row: dict, t: float) -> str:
    """The held-out whole-image PSNR of the returned state at ``t`` CPU-seconds, '–' when not scored."""
    c = [c for c in row["curve"] if c["seconds"] == t]
    return f"{c[0]['psnr']:.2f}" if c else "–"


def line(key: str, row: dict) -> str:
    scene = key.split("/")[0]
    rr = row.get("after_rerasterized")
    moved = f"{rr['psnr']:.2f}" if rr else "–"
    s = row.get("surface") or {}
    off = f"{s['mean_abs_offset']:.4f} / {s['bound']:.3f}" if s.get("bound") else "–"
    load = row.get("load_average") or {}
    return (f"| {scene} | {LABELS.get(row['row'], row['row'])} | {row['blend']} | "
            + " | ".join(cell(row, t) for t in (0.0, 10.0, 30.0, 60.0))
            + f" | {row['returned_from']['seconds']:g} | {moved} | {off} | {row['steps']} | "
            f"{load.get('start', float('nan')):.1f}–{load.get('end', float('nan')):.1f} | {commit(row)} |")


def section(results: Path) -> str | None:
    """Held-out PSNR at 0/10/30/60 CPU-s with the surface tuned, beside the default levers."""
    r = read(results, "finetune_surface.json")
    if not r or not r.get("rows"):
        return None
    notes = sorted({f"{k.split('/')[0]}: {row['mesh_note']}" for k, row in r["rows"].items() if row.get("mesh_note")})
    out = ["## Tuning the surface (`python -m bench finetune_surface`)", "",
           "`omnirecon finetune --tune surface` moves the mesh's vertices along their normals through the photometric "
           "loss across the sources (each pixel keeps its rasterized face and slides along its ray). Held-out whole-image "
           "PSNR (dB) of the returned state (the best on validation, the start a candidate) after 0, 10, 30 and 60 "
           "CPU-seconds (`--clock cpu --threads 1`, 4 held-out views at most); *moved mesh* is the returned mesh "
           "rasterized afresh (what the real-time renderer draws); offsets are the mean |offset| against the bound "
           "(scene units); load is the 1-minute load average at the row's start and end.", "",
           "| scene | tuned | blend | 0 s | 10 s | 30 s | 60 s | returned from (s) | moved mesh | offset / bound | "
           "steps | load | commit |", "|" + "---|" * 13]
    out += [line(k, row) for k, row in r["rows"].items()]
    return "\n".join([*out, "", *(f"Meshes, {n}" for n in notes), "", prov(r["provenance"]), ""])
