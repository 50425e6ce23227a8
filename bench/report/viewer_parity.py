"""BENCHMARKS.md section: the web viewer against the real-time mesh path (`python -m bench viewer_parity`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import prov, read


def _setting(s: dict, bundled: int | None = None) -> str:
    every = not s["sources"] or (bundled is not None and s["sources"] >= bundled)
    per_frame = "every training view" if every else f"{s['sources']} sources per frame"
    angle = f", {s['angle_sources']} per point{', source masks' if s.get('source_masks') else ''}" \
        if s["blend"] == "angle" else ""
    cracks = f", cracks {s['cracks']}" if s.get("cracks") else ""
    return f"{s['blend']} ({per_frame}{angle}), {s['fill']} fill{cracks}"


def _key(row: dict) -> str:
    return "_masked" if row.get("scored_by") == "objects" else ""


def _line(row: dict) -> str:
    key = _key(row)
    b = row["bundle"]
    return (f"| {row['scene']} ({len(row['held_out'])} views, {row['resolution'][0]}x{row['resolution'][1]}) | "
            f"{_setting(row['setting'], b['sources'])} | v{b['version']}, {b['sources']} sources, {b['megabytes']:g} MB"
            f"{', tuned weights' if row.get('tuned') else ''} | "
            f"{row['python' + key]:.2f} | {row['browser' + key]:.2f} | {row['parity']:.2f} | {row['max_diff']} / "
            f"{row['mean_diff']:.2f} | {row['browser_ms_per_frame']:.0f} / {row.get('browser_cpu_ms_per_frame', float('nan')):.0f} | "
            f"{row['python_cpu_ms_per_frame']:.0f} | "
            f"{row['load_average'][0]:.1f} | `{row.get('commit', '–')[:12]}` |")


def _off(row: dict) -> str:
    key = _key(row)
    steps = [f"{row['browser' + key]:.2f}"] + [f"without {r['off']} {r['psnr' + key]:.2f}" for r in row["browser_off"]]
    return f"| {row['scene']} | {' -> '.join(steps)} |"


def _gaps(row: dict) -> str:
    key = "psnr_masked" if "psnr_masked" in row["gaps"][0] and row["scene"].startswith("dtu") else "psnr"
    steps = [f"{g['rung']} {g[key]:.2f}" for g in row["gaps"]]
    return f"| {row['scene']} | {' -> '.join(steps)} |"


def section(results: Path) -> str | None:
    r = read(results, "viewer_parity.json")
    if not r or not r.get("rows"):
        return None
    out = ["## The web viewer against the real-time mesh path (`python -m bench viewer_parity`)", "",
           "Held-out views drawn by the bundle `omnirecon export` writes (headless Chromium, software WebGL2, as the "
           "bundle starts) and by `MeshRenderer` with the real-time setting of the scene's finetune record "
           "(`realtime_setting`, with the crack fill), at the scene's resolution. PSNR against the photos (over the "
           "object masks where finetune scores them, DTU; the whole image elsewhere), the browser's PSNR against "
           "`MeshRenderer`'s frames (whole image) and the largest / mean absolute difference between them in 8-bit "
           "levels; the browser's wall / CPU milliseconds per frame (SwiftShader on the CPU, all of Chromium's processes) "
           "beside `MeshRenderer`'s CPU milliseconds (1 thread). Pictures: `bench/results/figures/viewer_parity_<scene>.png` (photo | "
           "MeshRenderer | browser | 4x difference). Rows from an `omnirecon reconstruct` output (`--folders`) draw "
           "and export its mesh with the checkpoint its finetune stage saved (*tuned weights*), as the user's "
           "`export/viewer` holds it; the others the shipped omnirecon-tiny. Each row names the commit it ran at.", "",
           "| scene | setting | bundle | MeshRenderer dB | browser dB | browser vs MeshRenderer dB | max / mean diff | "
           "browser ms / CPU ms | MeshRenderer CPU ms | load | commit |", "|" + "---|" * 11]
    out += [_line(row) for row in r["rows"]]
    if any(row.get("browser_off") for row in r["rows"]):
        out += ["", "The browser's PSNR with the parts of the setting turned off in the viewer, one after the other:", "",
                "| scene | dB |", "|---|---|"] + [_off(row) for row in r["rows"] if row.get("browser_off")]
    out += ["", prov(r["provenance"]), ""]
    g = read(results, "viewer_parity_gaps.json")
    if g and g.get("rows"):
        out += ["What each gap between main's viewer and the real-time path cost, measured with `MeshRenderer` "
                "drawing what the viewer drew before (3 sources, the far fill or the background colour, no source "
                "masks, no cracks) and closing one gap at a time (`python -m bench viewer_parity --gaps`; DTU over "
                "the masks; a network blend's frame sources from one encoding of every view, as the bundle holds "
                "them, against each set encoded on its own):", "", "| scene | dB |", "|---|---|"]
        out += [_gaps(row) for row in g["rows"]] + ["", prov(g["provenance"]), ""]
    return "\n".join(out)
