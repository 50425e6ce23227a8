"""The end-to-end section of BENCHMARKS.md: a command at 1 and 2 threads (``--threads-ab``) read on the wall clock."""

import json


def test_the_threads_table_reads_the_goal_on_the_two_thread_wall_clock(tmp_path):
    from bench.report.end_to_end import section
    from omnirecon.provenance import provenance

    def run(n: int, wall: float, stages: dict) -> dict:
        return {"command": f"OMP_NUM_THREADS={n} omnirecon reconstruct photos --threads {n}",
                "whole": {"wall_s": wall, "cpu_s": wall * 1.2, "peak_rss_mb": 1900.0}, "load": [0.1, 1.0],
                "wall_s": stages, "cpu_s": stages}

    def ab(wall_2: float) -> dict:
        one, two = {"process": 100.0, "mesh": 50.0}, {"process": 60.0, "mesh": 30.0}
        per = {k: {"wall_1": one[k], "wall_2": two[k], "cpu_1": one[k], "cpu_2": two[k] * 1.5,
                   "wall_ratio": one[k] / two[k], "faster_with_2": True} for k in one}
        return {"runs": {"1": run(1, 310.0, one), "2": run(2, wall_2, two)}, "per_stage": per, "goal_s": 300.0,
                "provenance": provenance(seed=0)}

    (tmp_path / "end_to_end.json").write_text(json.dumps({"threads": {"reconstruct": ab(210.0)}}))
    text = section(tmp_path)
    assert "310.0 s wall at 1 thread" in text and "210.0 s wall at 2 threads" in text
    assert "the goal of 300 s on 2 cores: met" in text
    assert "| process | 100.0 | 60.0 | 100.0 | 90.0 |" in text
    (tmp_path / "end_to_end.json").write_text(json.dumps({"threads": {"reconstruct": ab(320.0)}}))
    assert "the goal of 300 s on 2 cores: short" in section(tmp_path)


def test_a_threads_run_without_its_goal_takes_the_goal_of_the_same_commands_row(tmp_path):
    from bench.report.end_to_end import section
    from omnirecon.provenance import provenance

    run = {"command": "omnirecon reconstruct photos --threads 1", "whole": {"wall_s": 280.0}, "load": [1.0]}
    ab = {"runs": {"1": run, "2": run}, "per_stage": {}, "provenance": provenance(seed=0)}
    row = {"command": "omnirecon reconstruct photos --threads 1", "verdict": {
        "goal_s": 300.0, "stages_total_cpu_s": 310.0, "over_goal_s": 10.0, "limiting_stage": "process",
        "limiting_stage_cpu_s": 100.0, "limiting_share": 0.3}, "whole": {"cpu_s": 1, "wall_s": 1, "peak_rss_mb": 1},
        "stages_cpu_s": {"process": 310.0}, "provenance": provenance(seed=0)}
    (tmp_path / "end_to_end.json").write_text(json.dumps({"reconstruct (lund)": row, "threads": {"reconstruct": ab}}))
    assert "the goal of 300 s on 2 cores: met" in section(tmp_path)
