"""The one place numeric options are checked (omnirecon/options.py): every numeric field of every command
has a rule, non-finite and out-of-range values are refused, and sizes are solved against the memory."""

from __future__ import annotations

import pytest

from omnirecon.cli import COMMANDS, _load
from omnirecon.errors import InputError
from omnirecon.options import RULES, _check_memory, check_options, numeric_fields, rule_for


def test_every_numeric_option_of_every_command_has_a_rule():
    missing = [(name, f) for name, spec in COMMANDS.items() for f in numeric_fields(_load(spec))
               if rule_for(name, f) is None]
    assert not missing, missing


def test_every_default_passes_its_rule():
    """The shipped defaults are inside their own rules (a rule that refuses a default is wrong)."""
    import dataclasses

    for name, spec in COMMANDS.items():
        for f in dataclasses.fields(_load(spec)):
            if f.name in numeric_fields(_load(spec)) and f.default not in (dataclasses.MISSING, None):
                values = f.default if isinstance(f.default, tuple) else (f.default,)
                rule = rule_for(name, f.name)
                assert all(rule.ok(v) for v in values), (name, f.name, f.default, rule)


def test_unused_rules_are_few():
    """Rules name real fields (a renamed option must not leave a dead rule behind)."""
    used = {f for spec in COMMANDS.values() for f in numeric_fields(_load(spec))}
    dead = [k for k in RULES if k.split(".")[-1] not in used]
    assert not dead, dead


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_is_refused_with_the_flag(value):
    import pathlib

    from omnirecon.workflows.finetune import FinetuneConfig

    cfg = FinetuneConfig(scene=pathlib.Path("s"), ckpt=pathlib.Path("c"), seconds=value)
    with pytest.raises(InputError, match="--seconds must be .* finite number.*got"):
        check_options("finetune", cfg)


def test_memory_limit_is_solved_for():
    with pytest.raises(InputError) as e:
        _check_memory([("--frames", "5000", 5000, lambda v: v * 1000.0)], available=2_000_000)
    assert "--frames 5000" in e.value.what and "--frames 1000 or less" in e.value.fix  # 50 % of 2 MB / 1 kB
    _check_memory([("--frames", "1000", 1000, lambda v: v * 1000.0)], available=2_000_000)


def test_notes_printed_while_parsing_reach_stderr(tmp_path, capsys):
    """MachineConfig's note on a --chunk above the memory ceiling is printed while tyro parses (whose stderr the
    CLI captures for its error box): it must still reach the user."""
    from omnirecon.chunk import ceiling
    from omnirecon.cli import main

    rc = main(["render", "--scene", str(tmp_path / "nope"), "--model", "floor", "--chunk", str(ceiling() + 1),
               "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and "omnirecon: note: --chunk" in err and str(tmp_path / "nope") in err.splitlines()[-1], err
