"""BENCHMARKS.md section: the hostile set's handled fraction per class and what was not handled."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import missing, read


def section(results: Path) -> str:
    r = read(results, "hostile.json")
    if r is None:
        return missing("hostile.json")
    lines = ["## Hostile inputs (`python -m bench hostile`)", "",
             f"A set of {r['cases']} hostile inputs of its own (not the malformed-input table's rows), each run in "
             "a forked child with a time limit and an address-space limit. Handled = exit 2, one stderr line naming "
             "the file or option with a fix, no traceback, nothing added/removed/changed (valid unusual photos and "
             "viewer requests: accepted / answered as they must).", "",
             f"**{r['handled']}/{r['cases']} handled ({100 * r['handled_fraction']:.1f} %)**; "
             + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in r["verdicts"].items() if k != "handled")
             + f"; {r['seconds']:.0f} s, load average {r['provenance'].get('load_average', ['?'])[0]:.1f}.", "",
             f"*Provenance: commit {r['provenance'].get('commit')}, {r['provenance'].get('date')}, torch "
             f"{r['provenance'].get('torch')}, {r['provenance'].get('torch_threads')} thread(s); time limit "
             f"{r['timeout_s']:.0f} s and +{r['extra_memory_gb']:.0f} GB address space per case.*", "",
             "| class | cases | handled |", "|---|---:|---:|"]
    lines += [f"| {k} | {v['cases']} | {v['handled']} |" for k, v in sorted(r["per_class"].items())]
    stalled = [x for x in r["results"] if x["args"].startswith("http_stalled")]
    if stalled:
        lines += ["", "Viewer under stalled connections (a request line, never the rest of the headers), then one "
                  "normal GET: " + "; ".join(f"{x['args'].split()[1]} stalled: {x['message'].split(' beside')[0]}"
                                             for x in stalled) + "."]
    lines += kill_sweep(results)
    if r["failures"]:
        lines += ["", "Not handled:", ""]
        lines += [f"- `{' '.join(f['args'])[:140]}` — {f['verdict']}: {f['message'][:160]}" for f in r["failures"][:20]]
    return "\n".join(lines) + "\n"


def kill_sweep(results: Path) -> list[str]:
    """Lines on `python -m bench resume_kill` (reconstruct killed with SIGKILL at each stage, then rerun)."""
    k = read(results, "resume_kill.json")
    if k is None:
        return []
    runs = k["runs"]
    return ["", "### reconstruct killed and rerun (`python -m bench resume_kill`)", "",
            f"`reconstruct` on {k['photos']} procedural photos ({k['photo_px']} px; uninterrupted "
            f"{k['uninterrupted_seconds']:.0f} s), killed with SIGKILL {k['kills']} times (after each stage is kept, "
            "and at evenly spaced moments), then rerun: **" f"{k['same_output']}/{k['kills']} reruns gave the "
            "uninterrupted output** (every file; records but for their timings). Two uninterrupted runs differ in: "
            f"{', '.join(k['uninterrupted_twice_differs']) or 'nothing'}. *Provenance: commit "
            f"{k['provenance'].get('commit')}, {k['provenance'].get('date')}, load average "
            f"{k['provenance'].get('load_average', ['?'])[0]:.1f}.*", "", "| killed | stages kept | rerun | same output |",
            "|---|---|---:|---|"] + [f"| {name} ({r['killed_at_s']} s) | "
                                      + ("(it ended before the kill)" if r["ended_before_kill"] else
                                         ", ".join(r["kept"]) or "-") + " | "
                                      f"{r['rerun_seconds']} s | {'yes' if r['same'] else r['differs']} |"
                                      for name, r in runs.items()]
