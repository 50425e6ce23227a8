"""``numbers``: every numeric option of every command (``omnirecon.options.numeric_fields``) with values a user
mistypes: ``nan``, ``inf``, ``-inf``, below and above its range, and a huge size."""

from __future__ import annotations

import typing
from pathlib import Path

from bench.hostile.fixtures import base_commands


def number_cases(p: dict[str, Path]) -> list[dict]:
    """Each numeric option of each command (but ``doctor``) with each value a user mistypes; refused naming the flag."""
    from omnirecon.cli import COMMANDS, _load
    from omnirecon.options import numeric_fields, rule_for

    base, tiny = base_commands(p), ["--threads", "1"]
    out: list[dict] = []
    for name, spec in COMMANDS.items():
        if name == "doctor":
            continue
        cls = _load(spec)
        hints = typing.get_type_hints(cls)
        for field in numeric_fields(cls):
            flag = "--" + field.replace("_", "-")
            text = str(hints[field])
            arity = 2 if "tuple[int, int]" in text else 1
            threads = tiny if "threads" in hints and field != "threads" else []
            for v in _mistyped(rule_for(name, field), "float" in text):
                out.append({"class": "numbers", "args": [*base[name], *threads, flag, *([v] * arity)],
                            "named": flag})
    return out


def _mistyped(rule, is_float: bool) -> list[str]:
    """The values a user mistypes for an option of ``rule`` (its range ``lo`` / ``hi``, None when open)."""
    values = ["nan", "inf", "-inf"] if is_float else ["1.5", "1e400"]
    if rule.lo is not None:
        lo = rule.lo - (1 if not is_float else max(1.0, abs(rule.lo)))
        values.append(str(int(lo)) if not is_float else repr(float(lo)))
    if rule.hi is not None:
        values.append(str(int(rule.hi * 10 + 1)) if not is_float else repr(float(rule.hi * 10 + 1)))
    return values
