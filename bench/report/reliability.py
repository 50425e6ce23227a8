"""BENCHMARKS.md section: Reliability (`python -m bench reliability`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import missing, prov, read


def section(results: Path) -> str:
    """Malformed inputs per command, fuzz cases per reader, kill -9 recovery (python -m bench reliability)."""
    r = read(results, "reliability.json")
    if r is None:
        return missing("reliability.json")
    m, f = r["malformed"], r["fuzz"]
    out = ["## Reliability (`python -m bench reliability`)", "",
           f"**Malformed inputs: {m['handled']} of {m['cases']} handled** (exit 2, one line naming the file with a "
           "fix clause, no traceback, nothing written; the table is `tests/commands/test_malformed.py`).", "",
           "| command | cases | handled |", "|---|---:|---:|"]
    out += [f"| {k} | {v['cases']} | {v['handled']} |" for k, v in m["per_command"].items()]
    out += ["", f"**Fuzzing: {f['cases']:,} generated inputs, {f['failures']} failures** "
            f"({f['examples_per_target']:,} per target; a failure is any exception other than a one-line "
            "InputError; `tests/data/test_fuzz.py`).", "",
            "| target | cases | InputError | read fine | failures |", "|---|---:|---:|---:|---:|"]
    out += [f"| {k} | {v['cases']:,} | {v['input_errors']:,} | {v['loaded']:,} | {v['failures']} |"
            for k, v in f["targets"].items()]
    for rerun in r.get("fuzz_reruns", []):  # targets rerun after fixing what the run above found
        out += ["", f"Rerun at commit `{rerun['commit']}` after {rerun['why']}:", "",
                "| target | cases | InputError | read fine | failures |", "|---|---:|---:|---:|---:|"]
        out += [f"| {k} | {v['cases']:,} | {v['input_errors']:,} | {v['loaded']:,} | {v['failures']} |"
                for k, v in rerun["targets"].items()]
    if r.get("kill"):
        out += ["", "**kill -9** at a random moment (5-75 % of an uninterrupted run, from an empty output), then the "
                "same command again to completion (train with `--resume`):", "",
                "| command | kills | finished first | partial result after the kill | hidden leftovers after the re-run "
                "| re-run failed |", "|---|---:|---:|---:|---:|---:|"]
        out += [f"| {k} | {v['kills']} | {v['finished_before_kill']} | {v['incomplete_after_kill']} | "
                f"{v['leftovers_after_rerun']} | {v['rerun_failed']} |" for k, v in r["kill"].items()]
        if r.get("kill_provenance"):
            out += ["", "kill -9 runs: " + prov(r["kill_provenance"])]
    for sig, rows in r.get("output_sets", {}).items():
        out += ["", f"**{sig} into a run that replaces a previous output of its own** (variants A and B alternate; "
                "the moment drawn in 5-75 % of an uninterrupted run): the output must be the old set or the complete "
                "new one; then the same command again to completion:", "",
                "| command | signals | old set kept | new set complete | mixed or missing | hung | re-run failed "
                "| leftovers after the re-run |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
        out += [f"| {k} | {v['signals']} | {v['old_set_kept']} | {v['new_set_complete']} | {v['mixed']} | {v['hung']} "
                f"| {v['rerun_failed']} | {v['leftovers_after_rerun']} |" for k, v in rows.items()]
    if r.get("concurrent"):
        out += ["", "**Two runs started together on one `--out`** (one must finish, the other be refused by the lock "
                "with one line; one complete output):", "",
                "| command | pairs | one finished, one refused | both finished | other | incomplete output | leftovers |",
                "|---|---:|---:|---:|---:|---:|---:|"]
        out += [f"| {k} | {v['pairs']} | {v['one_finished_one_refused']} | {v['both_finished']} | "
                f"{v['other'] + v['both_failed']} | {v['incomplete_output']} | {v['leftovers']} |"
                for k, v in r["concurrent"].items()]
    if r.get("outputs_provenance"):
        out += ["", "Output-set and concurrent runs: " + prov(r["outputs_provenance"])]
    out += ["", prov(r["provenance"])]
    return "\n".join(out)
