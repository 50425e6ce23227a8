"""The 256-px warm start's ship rule (`bench/train_256.py`) and its BENCHMARKS section."""

import json


def _row(name: str, p256: float, r256: float, p64: float, r64: float) -> dict:
    return {"name": name, "step": 7000, "cpu_s": 100.0,
            "256": {"scenes": {"synth:scene_901000": p256, "fox": r256}, "procedural": p256, "real": r256, "cpu_s": 9.0},
            "64": {"scenes": {"synth:scene_901000": p64, "fox": r64}, "procedural": p64, "real": r64, "cpu_s": 3.0}}


def test_the_run_replaces_the_weights_only_when_it_beats_at_256_px_and_keeps_64_px_else_ships_as_256_px_weights():
    from bench.train_256 import decide

    shipped = _row("shipped", 25.0, 22.0, 27.0, 26.0)
    assert decide(shipped, _row("run", 25.2, 22.3, 26.95, 25.95))[0] == "replace"
    assert decide(shipped, _row("run", 25.2, 22.05, 27.0, 26.0))[0] is None  # real +0.05: within the margin
    where, why = decide(shipped, _row("run", 25.5, 22.5, 26.5, 26.0))  # 64 px procedural -0.5
    assert where == "sizes" and why.startswith("ships as the checkpoint's 256-px weights (beats the shipped")


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
    assert "Decision: ships (replaces the checkpoint's weights)." in text
    assert "Half the scenes" not in text
    mixed = _row("ibrnet-tiny + 1400 steps at 256 px, half the scenes at 64 px", 25.2, 22.2, 26.5, 26.0)
    ships, why = decide(shipped, mixed)
    (tmp_path / "train_256_mix64.json").write_text(json.dumps({
        "provenance": provenance(seed=0), "model": "ibrnet-tiny", "size": 256, "mix": 64, "margin_db": 0.1,
        "command": "y", "rows": [shipped, mixed], "ships": ships, "decision": why}))
    text = section(tmp_path)
    assert "| ibrnet-tiny + 1400 steps at 256 px, half the scenes at 64 px | 7,000 | +100 | 25.20 | 22.20 |" in text
    assert ("**Half the scenes at 64 px** (`python -m bench train_256 --mix 64`" in text
            and "procedural 64 px -0.50, real 64 px +0.00. Decision: ships as the checkpoint's 256-px weights (beats "
                "the shipped checkpoint at 256 px, loses more than 0.1 dB at 64 px, where the checkpoint's own weights "
                "stay)." in text)


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


def test_ship_as_256_px_weights_keeps_the_own_weights_and_load_picks_by_size(tmp_path, monkeypatch):
    """``sizes``: the run's weights go to ``sizes/256/`` beside the untouched own weights, the card records the stage
    under ``sizes``, and loading for a 256-px render picks them while a 64-px one keeps the own weights."""
    import torch

    import bench.train_256 as t
    from omnirecon.engine.checkpoint import folder_for_size, load_checkpoint, save_checkpoint
    from omnirecon.engine.checkpoint_check import read_weights
    from omnirecon.models.registry import build_model

    monkeypatch.setattr(t, "ROOT", tmp_path)
    dest = tmp_path / "checkpoints" / "ibrnet-tiny"
    torch.manual_seed(0)
    render = {"render_coarse_samples": 16, "render_fine_samples": 16}  # the shipped render options
    save_checkpoint(dest, build_model("ibrnet-tiny", render), "ibrnet-tiny", step=7000, train_config={"resolution": 64})
    (dest / "card.json").write_text(json.dumps({"steps": 7000, "cpu_seconds": 8202.0, "resolution": 64}))
    (dest / "MODEL_CARD.md").write_text("# ibrnet-tiny\n")
    final = t.run_dir("ibrnet-tiny") / "checkpoints" / "final"
    torch.manual_seed(1)
    save_checkpoint(final, build_model("ibrnet-tiny"), "ibrnet-tiny", step=950, train_config={"resolution": 256},
                    extra={"cpu_s": 3500.0})
    own = (dest / "model.safetensors").read_bytes()
    rows = [_row("shipped", 25.0, 22.0, 27.0, 26.0), _row("run", 25.5, 22.5, 26.5, 26.0)]
    where, why = t.decide(*rows)
    t.ship("ibrnet-tiny", {"command": "python -m omnirecon.cli train x", "decision": why, "rows": rows,
                           "cpu_budget": 3600.0}, where=where)
    assert (dest / "model.safetensors").read_bytes() == own
    from omnirecon.engine.checkpoint import checkpoint_weights

    stored = read_weights(dest / "sizes" / "256" / "model.safetensors")
    assert stored and len(stored) < len(checkpoint_weights(final))  # only what differs: the seeds share some tensors
    loaded = checkpoint_weights(dest / "sizes" / "256")
    assert all(torch.equal(v, loaded[k]) for k, v in checkpoint_weights(final).items())
    assert json.loads((final / "meta.json").read_text())["model_config"].get("render_coarse_samples") is None
    card = json.loads((dest / "card.json").read_text())
    assert card["steps"] == 7000 and card["sizes"]["256"]["steps"] == 950
    assert "These weights are in `sizes/256/`" in (dest / "MODEL_CARD.md").read_text()
    assert folder_for_size(dest, 64) == dest and folder_for_size(dest, 128) == dest  # a tie keeps the own weights
    assert folder_for_size(dest, 129) == dest / "sizes" / "256" and folder_for_size(dest, 504) == dest / "sizes" / "256"
    assert folder_for_size(dest, None) == dest
    big, meta = load_checkpoint(dest, long_side=336)
    assert big.cfg.render_coarse_samples == 16 and big.cfg.render_fine_samples == 16  # renders as the own weights
    small, _ = load_checkpoint(dest, long_side=64)
    assert meta["step"] == 950
    differ = [k for k, v in big.state_dict().items() if not torch.equal(v, small.state_dict()[k])]
    assert differ  # the two sizes load different weights
    assert t.own_weights("ibrnet-tiny") != dest and not (t.own_weights("ibrnet-tiny") / "sizes").exists()


def test_a_full_render_row_that_beats_both_at_256_px_ships_as_the_256_px_weights(tmp_path):
    """``--full-render``: a state rendered with the trained sample counts wins the 256-px weights when it beats the
    shipped checkpoint (and a winning run) by more than the margin on both groups; the section lists it without
    64-px cells."""
    from bench.report.train_256 import section
    from bench.train_256 import decide
    from omnirecon.provenance import provenance

    shipped, run = _row("shipped ibrnet-tiny", 25.0, 22.0, 27.0, 26.0), _row("run", 25.3, 22.2, 26.5, 25.5)
    full = {"name": "run, full render", "step": 7950, "render": "full",
            "256": {"scenes": {"synth:scene_901000": 25.9, "fox": 22.8}, "procedural": 25.9, "real": 22.8}}
    where, why = decide(shipped, run, [full])
    assert where == "sizes:run, full render" and "beats the shipped checkpoint and the run" in why
    weak = {**full, "256": {**full["256"], "real": 22.25}}  # +0.05 over the run: within the margin
    assert decide(shipped, run, [weak])[0] == "sizes"
    (tmp_path / "train_256.json").write_text(json.dumps({
        "provenance": provenance(seed=0), "model": "ibrnet-tiny", "size": 256, "margin_db": 0.1,
        "command": "x --num-views-range 3 10", "rows": [shipped, run, full], "ships": where, "decision": why}))
    text = section(tmp_path)
    assert "| run, full render | 7,950 | – | 25.90 | 22.80 | **25.90** | **22.80** | – | – |" in text
    assert "run, full render minus shipped at 256 px: procedural +0.90, real +0.80." in text
    assert "K drawn from [3, 10]" in text


def test_own_weights_with_more_samples_ship_as_render_options_alone(tmp_path, monkeypatch):
    """``--samples N``: the shipped weights rendered with N samples per ray win the 256-px slot; ``sizes/256/`` then
    holds no tensor, a 256-px load gets the own weights with N samples, and the card says nothing was trained."""
    import torch

    import bench.train_256 as t
    from omnirecon.engine.checkpoint import checkpoint_weights, load_checkpoint, save_checkpoint
    from omnirecon.engine.checkpoint_check import read_weights
    from omnirecon.models.registry import build_model

    monkeypatch.setattr(t, "ROOT", tmp_path)
    dest = tmp_path / "checkpoints" / "gpnr-tiny"
    torch.manual_seed(0)
    save_checkpoint(dest, build_model("gpnr-tiny", {"render_samples": 24, "render_bf16": True}), "gpnr-tiny",
                    step=9695, train_config={"resolution": 64})
    (dest / "card.json").write_text(json.dumps({"steps": 9695, "cpu_seconds": 14632.0, "resolution": 64}))
    (dest / "MODEL_CARD.md").write_text("# gpnr-tiny\n")
    assert t.samples_render("gpnr-tiny", 48) == {"render_samples": 48, "render_bf16": True}
    state = t.with_render(t.own_weights("gpnr-tiny"), tmp_path / "s48", t.samples_render("gpnr-tiny", 48))
    shipped, run = _row("shipped gpnr-tiny", 25.0, 22.0, 27.0, 26.0), _row("run", 24.7, 22.3, 26.9, 25.3)
    more = {"name": "shipped gpnr-tiny, 48 samples", "step": 9695, "render": "samples",
            "256": {"scenes": {"synth:scene_901000": 25.3, "fox": 22.3}, "procedural": 25.3, "real": 22.3}}
    where, why = t.decide(shipped, run, [more])
    assert where == "sizes:shipped gpnr-tiny, 48 samples"
    t.ship("gpnr-tiny", {"command": "x", "decision": why, "rows": [shipped, run, more], "cpu_budget": 1.0},
           where=where, state=state)
    assert read_weights(dest / "sizes" / "256" / "model.safetensors") == {}
    big, meta = load_checkpoint(dest, long_side=336)
    small, _ = load_checkpoint(dest, long_side=64)
    assert big.cfg.render_samples == 48 and small.cfg.render_samples == 24 and meta["step"] == 9695
    assert all(torch.equal(v, small.state_dict()[k]) for k, v in big.state_dict().items())
    assert checkpoint_weights(dest / "sizes" / "256").keys() == checkpoint_weights(dest).keys()
    card = json.loads((dest / "card.json").read_text())
    assert card["steps"] == 9695 and card["sizes"]["256"]["steps"] == 0
    assert card["sizes"]["256"]["render"] == {"render_samples": 48, "render_bf16": True}
    text = (dest / "MODEL_CARD.md").read_text()
    assert "## Rendered at 256 px with other options" in text and "`render_samples=48`" in text
    assert "25.00 / 22.00 -> 25.30 / 22.30" in text
