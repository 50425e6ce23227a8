"""bench/train_tiny.py's record of a run's stages: a stage that ended early names the step it reached."""

import json

from bench.train_tiny import ended_at, stage_commands


def _latest(run, step: int) -> None:
    latest = run / "checkpoints" / "latest"
    latest.mkdir(parents=True, exist_ok=True)
    (latest / "meta.json").write_text(json.dumps({"step": step}))


def test_a_stage_stopped_early_records_the_step_it_reached(tmp_path):
    """SIGTERM or the CPU budget ended the run at step 38 of a 250-step schedule: the stage records --stop-at 38,
    so its command in the model card reproduces the state; a finished schedule records nothing, a --stop-at
    reached records itself, and a --stop-at cut short by SIGTERM records the step reached."""
    assert ended_at(tmp_path, 250, None) == {}  # no checkpoint yet
    _latest(tmp_path, 38)
    assert ended_at(tmp_path, 250, None) == {"stop_at": 38}
    assert ended_at(tmp_path, 250, 100) == {"stop_at": 38}
    _latest(tmp_path, 100)
    assert ended_at(tmp_path, 250, 100) == {"stop_at": 100}
    _latest(tmp_path, 250)
    assert ended_at(tmp_path, 250, None) == {}
    stage = {"cpu_budget": 700.0, "steps": 250, "threads": 1, "from_step": 38, **ended_at(tmp_path, 250, None)}
    (tmp_path / "stages.json").write_text(json.dumps([
        {"cpu_budget": 700.0, "steps": 500, "threads": 1, "from_step": 0, "stop_at": 38, "real_weight": "3.0"}, stage]))
    first, second = stage_commands("ibrnet-tiny", tmp_path, 700.0, 250, 1)
    assert "--steps 500 --threads 1 --stop-at 38" in first and "--real-weight 3.0" in first
    assert "--stop-at" not in second and "--steps 250" in second
