"""BENCHMARKS.md section: Speed (`python -m bench throughput`, `python -m bench fast_paths`, `python -m bench profile_models`)."""

from __future__ import annotations

import json
from pathlib import Path

from bench.report.common import prov


def section(results: Path) -> str | None:
    """Before/after throughput (reference twins vs fast-path defaults, one run), the fast paths' costs on a
    held-out scene and the per-stage profiles."""
    names = ("throughput.json", "fast_paths.json", "profile.json", "profile_fast.json")
    data = {n: json.loads((results / n).read_text()) for n in names if (results / n).is_file()}
    r = data.get("throughput.json", {"rows": []})
    rows = [row for row in r["rows"] if "reference" in row]
    if not rows and len(data) <= ("throughput.json" in data):
        return None
    lines = ["## Speed (`python -m bench throughput`, `python -m bench fast_paths`, `python -m bench profile_models`)", ""]
    if rows:
        lines += [f"Before = the fast paths of `omnirecon/models/fast.py` at their reference twins (fp32 eager, the "
                  f"code before them); after = their defaults. Both measured in the same run, interleaved repeat by "
                  f"repeat (median of {r['repeats']}), {r['provenance'].get('torch_threads')} thread(s), "
                  f"{r['device']}; load average at the end {r.get('loadavg_end')}.", "",
                  "| preset | train rays/s before | after | speed-up | render rays/s before | after | speed-up |",
                  "|---|---|---|---|---|---|---|"]
        for row in rows:
            ref = row["reference"]
            lines.append(f"| {row['preset']} | {ref.get('train_rays_per_s', '–')} | {row.get('train_rays_per_s', '–')} "
                         f"| {row.get('speedup_train', '–')}× | {ref['render_rays_per_s']} | {row['render_rays_per_s']} "
                         f"| {row['speedup_render']}× |")
        lines += ["", prov(r["provenance"])]
    else:
        lines += ["*Before/after throughput: not measured yet (`python -m bench throughput`).*"]
    fp = data.get("fast_paths.json")
    if fp:
        lines += ["", "Fast paths on a held-out procedural scene (`python -m bench fast_paths`; speed-ups against the "
                  "reference in the same run; `surface_N`: the fine pass on N importance samples around the coarse "
                  "surface only):", "",
                  "| model | variant | render (s) | speed-up | PSNR vs GT | PSNR vs reference | max abs diff | "
                  "depth abs-rel vs GT | depth abs-rel vs reference | coarse-pass depth abs-rel vs GT |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for m in fp["models"]:
            for row in m["rows"]:
                lines.append(f"| {m['model']} ({m['weights']}) | {row['variant']} | {row['seconds']} | "
                             f"{row['speedup']}× | {row['psnr_gt']} | {row['psnr_vs_reference']} | "
                             f"{row['max_abs_vs_reference']} | {row.get('depth_absrel_gt', '–')} | "
                             f"{row.get('depth_absrel_vs_reference', '–')} | {row.get('coarse_depth_absrel_gt', '–')} |")
        if "compile" in fp:
            c = fp["compile"]
            lines += ["", f"`torch.compile` of {c['preset']}'s {c['module']} ({c['rays']} rays x {c['samples']} "
                      f"samples, inference): compile {c['compile_s']} s, then {c['eager_ms']} ms eager vs "
                      f"{c['compiled_ms']} ms compiled ({c['speedup']}×)."]
        lines += ["", prov(fp["provenance"])]
    for name, what in (("profile.json", "reference twins (fp32 eager)"), ("profile_fast.json", "fast-path defaults")):
        if name in data:
            lines += ["", f"Where the time goes, {what} (`python -m bench profile_models`: share of the wall time per stage, "
                      "self times; one thread; peak RSS of a fresh process per row):", "", profile_table(data[name]),
                      "", prov(data[name]["provenance"])]
    return "\n".join(lines)


def profile_table(r: dict) -> str:
    """Share of the wall time per stage (the stages as ``python -m bench profile_models`` folds them)."""
    cols = ["encode", "projection+sampling", "aggregation", "ray transformer", "compositing", "importance sampling",
            "fine pass", "backward", "optimizer", "other"]
    lines = ["| preset | mode | wall (s) | rays/s | " + " | ".join(cols) + " | peak RSS (MB) |",
             "|---|---|---|---|" + "---|" * len(cols) + "---|"]
    for row in r["rows"]:
        s = r["stages"][f"{row['preset']}/{row['mode']}"]
        cells = [f"{100 * s[c] / row['wall_s']:.0f}%" if c in s else "–" for c in cols]
        lines.append(f"| {row['preset']} | {row['mode']} | {row['wall_s']} | {row['rays_per_s']} | " + " | ".join(cells)
                     + f" | {row['peak_rss_mb']} |")
    return "\n".join(lines)
