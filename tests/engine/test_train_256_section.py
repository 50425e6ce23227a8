"""The 256-px warm start's ship rule (`bench/train_256.py`) and its BENCHMARKS section."""

import json


def _row(name: str, p256: float, r256: float, p64: float, r64: float) -> dict:
    return {"name": name, "step": 7000, "cpu_s": 100.0,
            "256": {"scenes": {"synth:scene_901000": p256, "fox": r256}, "procedural": p256, "real": r256, "cpu_s": 9.0},
            "64": {"scenes": {"synth:scene_901000": p64, "fox": r64}, "procedural": p64, "real": r64, "cpu_s": 3.0}}


def test_the_run_ships_only_when_it_beats_at_256_px_and_keeps_64_px():
    from bench.train_256 import decide

    shipped = _row("shipped", 25.0, 22.0, 27.0, 26.0)
    assert decide(shipped, _row("run", 25.2, 22.3, 26.95, 25.95))[0]
    assert not decide(shipped, _row("run", 25.2, 22.05, 27.0, 26.0))[0]  # real +0.05: within the margin
    no, why = decide(shipped, _row("run", 25.5, 22.5, 26.5, 26.0))  # 64 px procedural -0.5
    assert not no and why == "not shipped (beats the shipped checkpoint at 256 px, loses more than 0.1 dB at 64 px)"


def test_section_shows_both_rows_and_the_decision(tmp_path):
    from bench.report.train_256 import section
    from bench.train_256 import decide
    from omnirecon.provenance import provenance

    assert section(tmp_path) is None
    shipped, run = _row("shipped ibrnet-tiny", 25.0, 22.0, 27.0, 26.0), _row("ibrnet-tiny + 900 steps", 25.3, 22.4,
                                                                               27.0, 26.0)
    ships, why = decide(shipped, run)
    (tmp_path / "train_256.json").write_text(json.dumps({
        "provenance": provenance(seed=0), "model": "ibrnet-tiny", "size": 256, "margin_db": 0.1, "command": "x",
        "rows": [shipped, run], "ships": ships, "decision": why}))
    text = section(tmp_path)
    assert "| shipped ibrnet-tiny | 7,000 | +100 | 25.00 | 22.00 | **25.00** | **22.00** | **27.00** | **26.00** |" in text
    assert "Run minus shipped (ibrnet-tiny + 900 steps): procedural 256 px +0.30, real 256 px +0.40, procedural 64 px +0.00" in text
    assert "Decision: ships." in text
    assert "Half the scenes" not in text
    mixed = _row("ibrnet-tiny + 1400 steps at 256 px, half the scenes at 64 px", 25.2, 22.2, 26.5, 26.0)
    ships, why = decide(shipped, mixed)
    (tmp_path / "train_256_mix64.json").write_text(json.dumps({
        "provenance": provenance(seed=0), "model": "ibrnet-tiny", "size": 256, "mix": 64, "margin_db": 0.1,
        "command": "y", "rows": [shipped, mixed], "ships": ships, "decision": why}))
    text = section(tmp_path)
    assert "| ibrnet-tiny + 1400 steps at 256 px, half the scenes at 64 px | 7,000 | +100 | 25.20 | 22.20 |" in text
    assert ("**Half the scenes at 64 px** (`python -m bench train_256 --mix 64`" in text
            and "procedural 64 px -0.50, real 64 px +0.00. Decision: not shipped (beats the shipped checkpoint at 256 "
                "px, loses more than 0.1 dB at 64 px)." in text)


def test_ship_replaces_the_checkpoint_and_adds_the_stage_to_its_card(tmp_path, monkeypatch):
    """``--ship`` copies the run's final weights over the shipped ones and sums steps and CPU seconds on the card."""
    import bench.train_256 as t

    monkeypatch.setattr(t, "ROOT", tmp_path)
    dest = tmp_path / "checkpoints" / "ibrnet-tiny"
    dest.mkdir(parents=True)
    (dest / "model.safetensors").write_bytes(b"old")
    (dest / "meta.json").write_text(json.dumps({"step": 7000}))
    (dest / "training_curve.png").write_bytes(b"png")
    (dest / "card.json").write_text(json.dumps({"steps": 7000, "cpu_seconds": 8202.0, "wall_seconds": 100.0,
                                                "cpu_budget_s": 8500.0, "stages": ["a"], "resolution": 64}))
    (dest / "MODEL_CARD.md").write_text("# ibrnet-tiny\n")
    final = t.run_dir("ibrnet-tiny") / "checkpoints" / "final"
    final.mkdir(parents=True)
    (final / "model.safetensors").write_bytes(b"new")
    (final / "meta.json").write_text(json.dumps({"step": 950, "extra": {"cpu_s": 3500.0, "elapsed_s": 4000.0}}))
    rows = [_row("shipped", 25.0, 22.0, 27.0, 26.0), _row("run", 25.3, 22.4, 27.0, 26.0)]
    t.ship("ibrnet-tiny", {"command": "python -m omnirecon.cli train x", "decision": "ships: y", "rows": rows,
                           "cpu_budget": 3600.0})
    card = json.loads((dest / "card.json").read_text())
    assert (dest / "model.safetensors").read_bytes() == b"new" and (dest / "training_curve.png").is_file()
    assert card["steps"] == 7950 and card["cpu_seconds"] == 11702.0 and card["cpu_budget_s"] == 12100.0
    assert card["stages"] == ["a", "python -m omnirecon.cli train x"] and card["continued"]["resolution"] == 256
    text = (dest / "MODEL_CARD.md").read_text()
    assert "## Continued at 256 px" in text and "25.00 / 22.00 -> 25.30 / 22.40" in text
    assert not dest.with_name("ibrnet-tiny.tmp").exists()
