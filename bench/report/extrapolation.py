"""BENCHMARKS.md section: Away from the photos (`python -m bench extrapolation`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.report.common import prov, read

INTRO = (
    "What a user sees away from the photos (issue 42). Each scene's **extrapolation split**: the training views lie "
    "within one arc of azimuth (at most 100 degrees; a walk: its first stretch), the test views 10-30 degrees beyond it "
    "(a walk: its last stretch, 4 photos). The mesh is made from the training views alone with `omnirecon mesh`'s "
    "defaults for the scene kind and rendered by the real-time mesh path as `reconstruct`'s video renders it. "
    "*Held-out*: the test views against their photos (whole image; DTU also over the object mask). *Path*: the camera "
    "path a user watches (the photos' arc and 15 degrees past each end; a walk goes through its photos), 24 frames; on "
    "procedural scenes against the generator's exact images at those poses. *Defects*: the share of a frame's pixels "
    "drawn by faces no photo supports (completion's fills, faces no training view sees within 75 degrees of their "
    "normal, connected pieces under 5 % of the bounds' diagonal), mean over the frames, and the worst frame. Surfaces: "
    "`fusion` is the TSDF with completion's fills (the pipeline before issue 42), `coherent` the screened-Poisson "
    "surface of the depth several views confirm with its background layer (`omnirecon/mesh/surface.py`); `exact` is "
    "the procedural scene's exact mesh through the same mesh path. CPU-s: the surface from cached depth maps, one "
    "thread, on a machine shared with other work (compare within a row only). A picture per row: test view truth | "
    "render | its defect faces (fills red, unseen blue, fragments yellow), then the path's first frame, its worst frame "
    "and that frame's defect faces. `coherent[fine=\"tsdf\"]`: the coherent surface on the fused TSDF surface instead "
    "of Poisson's. lund is posed with sequential matching of 4,096 features (`bench/extrapolation.posed_lund`): a "
    "street walked out and back, whose last 4 photos look around a corner no training photo shows. `mesh --surface "
    "auto` (the default, `omnirecon.mesh.build.default_surface`) takes `coherent` on a walk (lund: fewer defect pixels "
    "on the path with either pose of lund; held-out PSNR higher with the first pose, lower with this one) and "
    "`fusion` elsewhere: on the interpolated held-out views of \"Depth sources\" (rows `, coherent`) the coherent "
    "surface loses on fern and the demo scene, and on objects without masks neither coherent variant wins on both "
    "fox and ethiopianHead.")


def f(x, fmt: str = "{:.2f}") -> str:
    return "–" if x is None or x != x else fmt.format(x)


def pct(x) -> str:
    return "–" if x is None or x != x else f"{100 * x:.1f} %"


def line(r: dict) -> str:
    h, p = r["held_out"], r["path"]
    masked = f" ({f(h.get('psnr_masked'))} mask)" if h.get("psnr_masked") is not None else ""
    return (f"| {r['scene']} | {r['surface']} | {len(r['train'])} / {len(r['test'])} | {f(h.get('psnr'))}{masked} | "
            f"{pct(h.get('coverage'))} | {pct(h.get('defect_any'))} ({pct(h.get('defect_fill'))} / "
            f"{pct(h.get('defect_unseen'))} / {pct(h.get('defect_small'))}) | {f(p.get('psnr'))} | "
            f"{pct(p.get('defect_any'))} / {pct(p.get('worst_defect'))} | {f(r['cpu_seconds']['surface'], '{:.0f}')} | "
            f"`{r.get('commit', '–')}` | [picture]({r['figure']}) |")


def summary(rows: list[dict]) -> list[str]:
    """Means per surface: procedural (and the exact mesh's), real scenes; the gap and the goals."""
    out = []
    by = {}
    for r in rows:
        kind = "procedural" if r["scene"].startswith(("demo", "synth_")) else "real"
        by.setdefault((kind, r["surface"]), []).append(r)
    for (kind, surface), rs in sorted(by.items()):
        held = [r["held_out"].get("psnr") for r in rs if r["held_out"].get("psnr") is not None]
        path = [r["path"].get("psnr") for r in rs if r["path"].get("psnr") is not None]
        defects = [r["path"]["defect_any"] for r in rs]
        out.append(f"- {kind}, `{surface}` ({len(rs)} scenes: {', '.join(r['scene'] for r in rs)}): held-out "
                   f"{f(np.mean(held) if held else None)} dB" + (f", path {f(np.mean(path))} dB" if path else "")
                   + f", path defects {pct(np.mean(defects))} (worst frame of any scene {pct(max(r['path']['worst_defect'] for r in rs))})")
    return out


def section(results: Path) -> str | None:
    r = read(results, "extrapolation.json")
    if not r or not r.get("rows"):
        return None
    rows = sorted(r["rows"], key=lambda x: (x["scene"], x["surface"]))
    out = ["## Away from the photos", "", INTRO, "",
           "| scene | surface | train / test views | held-out PSNR (dB) | coverage | defects (fill / unseen / fragments) | "
           "path PSNR (dB) | path defects mean / worst frame | CPU-s | commit | picture |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    out += [line(row) for row in rows]
    out += ["", "Means:", "", *summary(rows), "", "Provenance of the last run (each row names the commit it measured):",
            prov(r["provenance"]), ""]
    return "\n".join(out)
