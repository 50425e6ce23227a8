"""Command-line parse errors as one line: tyro draws a multi-line box (Unicode or ASCII, depending on the
terminal); :func:`parse_error_line` keeps what the box says (which flag is unknown, missing or malformed)
and adds the fix."""

from __future__ import annotations

import re

EDGE = "\u2502\u2503|+\u256d\u256e\u2570\u256f\u250c\u2510\u2514\u2518"  # vertical bars and corners
RULE = re.compile(r"^[\s\-\u2500\u2501=]*$")  # a horizontal rule (nothing but dashes)


def parse_error_line(text: str, command: str | None) -> str:
    """One line from tyro's error box ``text``: its first section (the lines before the first rule inside
    the box), prefixed with the box title when the section does not already start with it, then a fix
    clause pointing at ``--help`` of ``command``."""
    lines = [ln.strip().strip(EDGE).strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    title = lines[0].strip("-\u2500 ").strip() if lines else ""
    body: list[str] = []
    for line in lines[1:]:
        if RULE.match(line) or line.startswith("For full helptext"):
            if body or line.startswith("For full helptext"):
                break
            continue
        body.append(line)
    what = re.sub(r"\s+", " ", " ".join(body)).strip() or title or "invalid command line"
    if title and not what.lower().startswith(title.lower().split()[0]):
        what = f"{title.lower()}: {what}"
    help_cmd = f"omnirecon {command} --help" if command else "omnirecon --help"
    return f"{what[:300]} (fix: see `{help_cmd}` for the flags)"
