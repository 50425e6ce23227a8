"""BENCHMARKS.md sections: render levers of the tiny presets, each fast-path switch against its reference twin,
and torch.compile's cold and warm start (`python -m bench tiny_levers`, `tiny_levers --switches`, `compile_cache`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import prov, read


def section(results: Path) -> str | None:
    # later per-model runs (tiny_levers_<model>.json) replace that model's rows of the main run
    later = [read(results, f.name) for f in sorted(results.glob("tiny_levers_*.json"))]
    parts = []
    if r := read(results, "tiny_levers.json"):
        parts.append(_levers(r, later))
    parts += [f(r) for f, name in ((_switches, "switches.json"), (_compile, "compile_cache.json"))
              if (r := read(results, name))]
    return "\n".join(parts) if parts else None


def _table(r: dict) -> list[str]:
    """Rows of one tiny_levers run: each candidate's speed-up and PSNR per scene."""
    names = [s["name"] for s in r["scenes"]]
    lines = ["| preset | candidate | CPU s | speed-up | PSNR (dB) | dPSNR | " + " | ".join(names) + " |",
             "|---|---|---|---|---|---|" + "---|" * len(names)]
    for m in r["models"]:
        for row in m["rows"]:
            best = row["speedup"] >= 3 and row["dpsnr"] >= -0.1
            cand = f"**{row['candidate']}**" if best else row["candidate"]
            lines.append(f"| {m['model']} | {cand} | {row['cpu_s']} | {row['speedup']}× | {row['psnr_mean']} | "
                         f"{row['dpsnr']:+.3f} | " + " | ".join(str(row["psnr"].get(n, "–")) for n in names) + " |")
    return lines


def _levers(r: dict, later: list[dict]) -> str:
    """BENCHMARKS.md section: per tiny preset, each candidate's speed-up over the reference twins and its PSNR."""
    scenes = ", ".join(f"{s['name']} ({s['size'][0]}x{s['size'][1]})" for s in r["scenes"])
    lines = ["## Render levers of the tiny presets (`python -m bench tiny_levers`)", "",
             f"Goal: 3x the render throughput the tiny presets had before the fast paths (their reference twins: fp32 "
             f"eager, every switch off) at equal quality. Render CPU seconds of every target (encode + `render_view`, "
             f"one thread, K = {r['k']}, {r['targets_per_scene']} target(s) per scene; candidates interleaved "
             f"{r['rounds']} times, fastest kept) on {scenes}; speed-up against the reference in the same run; PSNR "
             "against the ground truth (mean over the scenes) and its difference from the reference render's "
             "(dPSNR). `default`: the full render with today's fast paths; `checkpoint`: what every command now renders, "
             "the checkpoint's own render options (its `meta.json`). `fine_N`/`coarse_N`/`samples_N`: the model's sample "
             "counts changed at render time, no retraining; `render_C_F`: IBRNet's `render_coarse_samples` C and "
             "`render_fine_samples` F, each sample standing for the trained ones it replaces (index code in trained "
             "positions, density scaled); `coarse_only`: no fine pass; `surface_N`: the fine pass on N "
             "importance samples only. "
             f"Load average at the start {r['loadavg_start']}, at the end {r['loadavg_end']}.", ""]
    redone = {m["model"] for x in later for m in x["models"]}
    main = {**r, "models": [m for m in r["models"] if m["model"] not in redone]}
    lines += _table(main)
    lines += ["", "Bold: at least 3x the reference with at most 0.1 dB lost.", "", prov(r["provenance"])]
    for x in later:
        models = ", ".join(m["model"] for m in x["models"])
        scenes = ", ".join(f"{s['name']} ({s['size'][0]}x{s['size'][1]})" for s in x["scenes"])
        lines += ["", f"{models}, measured again after its checkpoint's render options changed (same protocol: K = "
                  f"{x['k']}, {x['targets_per_scene']} target(s) per scene, {x['rounds']} round(s); {scenes}; load "
                  f"{x['loadavg_start']} -> {x['loadavg_end']}), replacing its rows of the first run:", ""]
        lines += _table(x)
        lines += ["", prov(x["provenance"])]
    return "\n".join(lines) + "\n"


def _switches(r: dict) -> str:
    """BENCHMARKS.md section: each fast-path switch alone over the reference, and the defaults without it."""
    lines = ["## Each fast-path switch against its reference twin (`python -m bench tiny_levers --switches`)", "",
             "Render CPU seconds (encode + `render_view`, random weights, `bench/profile_models.py`'s case, one "
             f"thread; sides interleaved {r['rounds']} times, fastest kept): `only_X` is the reference with switch "
             "X on, `without_X` the defaults with X at its reference twin. Speed-up against the reference in the "
             f"same run. Load average at the start {r['loadavg_start']}, at the end {r['loadavg_end']}.", ""]
    for p in r["presets"]:
        lines += [f"**{p['preset']}** ({p['sources']} sources, {p['target'][0]}x{p['target'][1]} target)", "",
                  "| side | CPU s | speed-up | max abs diff to the reference |", "|---|---|---|---|"]
        lines += [f"| {x['side']} | {x['cpu_s']} | {x['speedup']}× | {x['max_abs_vs_reference']:.2g} |" for x in p["rows"]]
        lines.append("")
    return "\n".join([*lines, prov(r["provenance"])]) + "\n"


def _compile(r: dict) -> str:
    """BENCHMARKS.md section: cold and warm start of ``OMNIRECON_FAST=compile=1`` and its steady render."""
    s = r["summary"]
    w, h = r["size"]
    repay = s["renders_to_repay_warm"]
    lines = ["## torch.compile with a persistent cache: cold and warm start (`python -m bench compile_cache`)", "",
             f"{r['preset']} (random weights), one {w}x{h} view from 3 sources, one thread, each side a fresh "
             "process in the order eager, cold (empty inductor cache), warm (same cache, new process), eager; CPU "
             "seconds including inductor's compile workers. First render = compile + render.", "",
             "| side | first render CPU s (wall) | steady render CPU s |", "|---|---|---|"]
    lines += [f"| {x['side']} | {x['first_cpu_s']} ({x['first_wall_s']}) | {x['steady_cpu_s']} |" for x in r["runs"]]
    lines += ["", f"Compiled steady render {s['steady_speedup']}× eager; start-up cost {s['cold_overhead_cpu_s']} CPU s "
              f"cold, {s['warm_overhead_cpu_s']} CPU s warm"
              + (f", repaid after {repay} renders (warm)." if repay is not None else ", never repaid (no steady gain).")
              + f" Load average at the start {r['loadavg_start']}, at the end {r['loadavg_end']}.", "",
              prov(r["provenance"])]
    return "\n".join(lines) + "\n"
