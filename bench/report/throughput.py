"""BENCHMARKS.md section: Throughput (`python -m bench throughput`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import missing, prov, read


def section(results: Path) -> str:
    r = read(results, "throughput.json")
    if r is None:
        return missing("throughput.json")
    lines = [
        "## Throughput (`python -m bench throughput`)",
        "",
        f"Device: {r['device']}. A training step = encode the source views + render the ray batch + MSE + "
        f"backward + AdamW step. Rendering = `render_view` of a full image (paper presets: of a small view of `render_rays` pixels) "
        f"with features encoded once. Median of {r['repeats']} timed repeats after a warm-up; "
        f"{r['provenance'].get('torch_threads')} torch thread(s), load average "
        f"{r['provenance'].get('loadavg_1min')} at the start and {r.get('loadavg_end', '?')} at the end: absolute "
        "rays/s depend on both (the machine's 2 cores are shared); the Speed section's before/after ratios do not.",
        "",
        "| preset | parameters | source views | train rays / step | train step (s) | train rays/s | "
        "render rays/s | render FPS |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in r["rows"]:
        lines.append(f"| {row['preset']} | {row['params']:,} | {row['source_views']} | {row['rays_per_step']} | "
                     f"{row.get('train_step_s', '–')} | {row.get('train_rays_per_s', '–')} | "
                     f"{row['render_rays_per_s']} | {row['render_fps_at_resolution']} at {row['resolution']}² |")
    earlier = [row for row in r["rows"] if "provenance" in row]
    if earlier:
        lines += ["", "Rows measured in an earlier run of the same script (`--presets` re-measures some rows and keeps "
                  "the others): " + "; ".join(f"{row['preset']}: {prov(row['provenance'])}" for row in earlier)]
    return "\n".join([*lines, "", prov(r["provenance"])])
