"""BENCHMARKS.md section: `make demo` on a fresh clone and `reconstruct` of photos, CPU seconds per stage and the
stage that limits against the goals (`python -m bench end_to_end`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import prov, read


def section(results: Path) -> str | None:
    r = read(results, "end_to_end.json")
    return _end_to_end(r) if r else None


def _end_to_end(r: dict) -> str:
    """BENCHMARKS.md section: per command, CPU seconds per stage at one thread, the goal and what limits."""
    lines = ["## End to end: `make demo` and `reconstruct` (`python -m bench end_to_end`)", "",
             "One thread, stage clocks reading process CPU seconds (what a quiet machine would take at one thread; "
             "every wall budget, e.g. 60 s of tuning, becomes CPU seconds too; the process stage adds its SfM child's CPU "
             "seconds, every thread, where the run recorded them); whole-command CPU and wall seconds from "
             "`/usr/bin/time` (without that child, which a fork server starts) with the load average beside them (wall "
             "on the shared cores is mostly the scheduler).", ""]
    for name, run in r.items():
        if name in ("mesh_sources", "threads"):
            continue
        v, w = run["verdict"], run["whole"]
        lines += [f"**{name}** (`{run['command']}`): stages {v['stages_total_cpu_s']} CPU s against the goal of "
                  f"{v['goal_s']:.0f} s ({v['over_goal_s']:+.0f} s); the limit is **{v['limiting_stage']}** with "
                  f"{v['limiting_stage_cpu_s']} CPU s ({100 * v['limiting_share']:.0f} %). Whole command {w['cpu_s']} "
                  f"CPU s, {w['wall_s']} s wall at load {run.get('load')}, peak RSS {w['peak_rss_mb']} MB."
                  + (f" `make setup` before it: {run['setup']['cpu_s']} CPU s, {run['setup']['wall_s']} s wall."
                     if run.get("setup") else "")
                  + (" Fine-tuning (held-out, mesh path, visibility test): whole image "
                     + " -> ".join(f"{x:.2f}" for x in run["finetune"]["whole_image"]) + " dB at coverage "
                     f"{run['finetune']['coverage']:.0%}, {run['finetune']['steps']} steps." if run.get("finetune") else "")
                  + (f" Held-out mesh-path PSNR (whole image) {run['psnr_before_after'][0]:.2f} -> "
                     f"{run['psnr_before_after'][1]:.2f} dB; {run['photos_registered']} photos posed; camera path "
                     f"{run['path_fps']} FPS." if run.get("psnr_before_after") else ""),
                  "",
                  "| stage | CPU s | share | peak RSS MB |", "|---|---|---|---|"]
        total = v["stages_total_cpu_s"]
        peaks = run.get("stages_peak_rss_mb") or {}  # the stage's own peak (recorded since reconstruct has it)
        lines += [f"| {k} | {s} | {100 * s / total:.0f} % | {peaks.get(k, '–')} |" for k, s in run["stages_cpu_s"].items()]
        lines += ["", prov(run["provenance"]), ""]
    if r.get("mesh_sources"):
        lines += ["Reconstruct's mesh stage from cheaper depth sources (`omnirecon mesh --views all` on the scene "
                  "reconstruct processed, one thread, CPU seconds per stage; `render` is the depth source):", "",
                  "| depth source | images -> mesh CPU s | render | fuse | clean | whole command CPU s |",
                  "|---|---|---|---|---|---|"]
        for label, m in r["mesh_sources"].items():
            st = m["stages_cpu_s"]
            lines.append(f"| {label} | {st.get('images_to_mesh')} | {st.get('render')} | {st.get('fuse')} | "
                         f"{st.get('clean')} | {(m['whole'] or {}).get('cpu_s', '–')} |")
        lines.append("")
    for kind, ab in (r.get("threads") or {}).items():  # the goal: the run's, else the same command's 1-thread row's
        goal = ab.get("goal_s") or next((run["verdict"]["goal_s"] for name, run in r.items()
                                         if name.split(" ")[0] == kind and "verdict" in run), None)
        lines += _threads(kind, ab, goal)
    return "\n".join(lines)


def _threads(kind: str, ab: dict, goal: float | None) -> list[str]:
    """The command at 1 and 2 torch threads back to back (``--threads-ab``): wall and CPU seconds per stage, real
    clocks, and the goal (seconds) read on the 2-thread wall time."""
    one, two = ab["runs"]["1"], ab["runs"]["2"]
    verdict = (f"; the goal of {goal:.0f} s on 2 cores: {'met' if two['whole']['wall_s'] <= goal else 'short'}"
               if goal else "")
    lines = [f"**{kind} at 1 and 2 threads** (`python -m bench end_to_end --threads-ab {kind}`: "
             f"`{one['command']}`, then the same at 2 threads, back to back, real clocks): whole command "
             f"{one['whole']['wall_s']} s wall at 1 thread (load {one['load']}), {two['whole']['wall_s']} s wall at 2 "
             f"threads (load {two['load']}){verdict}. Per stage, wall and process CPU seconds:", "",
             "| stage | wall 1 thread | wall 2 threads | CPU 1 thread | CPU 2 threads |", "|---|---|---|---|---|"]
    lines += [f"| {k} | {s['wall_1']:.1f} | {s['wall_2']:.1f} | {s['cpu_1']:.1f} | {s['cpu_2']:.1f} |"
              for k, s in ab["per_stage"].items()]
    return [*lines, "", prov(ab["provenance"]), ""]
