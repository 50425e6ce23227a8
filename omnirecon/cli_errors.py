"""Command-line parse errors as one line: tyro draws a multi-line box; :func:`parse_error_line` keeps
what the box says (which flag is unknown, missing or malformed) and adds the fix."""

from __future__ import annotations

import re

BOX = re.compile(r"[\u2500-\u257f]+")  # box-drawing characters


def parse_error_line(text: str, command: str | None) -> str:
    """One line from tyro's error box ``text``: its title and the lines before the first rule, then a fix
    clause pointing at ``--help`` of ``command``."""
    lines = [BOX.sub(" ", ln).strip() for ln in text.splitlines()]
    title, body = "", []
    for raw, ln in zip(text.splitlines(), lines):
        if not ln:
            if body and "\u2500" in raw:  # the rule after the first section
                break
            continue
        if not title and raw.lstrip().startswith("\u256d"):
            title = ln
            continue
        if ln.startswith("For full helptext"):
            break
        body.append(ln)
    what = " ".join(body) or title or "invalid command line"
    what = re.sub(r"\s+", " ", what)
    if title and not what.lower().startswith(title.lower().split()[0]):
        what = f"{title.lower()}: {what}"
    help_cmd = f"omnirecon {command} --help" if command else "omnirecon --help"
    return f"{what[:300]} (fix: see `{help_cmd}` for the flags)"
