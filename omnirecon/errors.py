"""User-facing errors.

Every problem caused by the user's input (a missing file, a malformed matrix, a bad flag) raises
:class:`InputError`. The CLI prints it as one line, ``omnirecon: error: <path>: <what> (fix: <how>)``,
and exits with code 2; ``--verbose`` adds the traceback.
"""

from __future__ import annotations

from pathlib import Path

EXIT_BAD_INPUT = 2


class InputError(Exception):
    """Bad user input: names the offending file (if any), what is wrong and how to fix it."""

    def __init__(self, what: str, path: str | Path | None = None, fix: str | None = None):
        self.what = what
        self.path = None if path is None else Path(path)
        self.fix = fix
        super().__init__(self.one_line())

    def one_line(self) -> str:
        parts = []
        if self.path is not None:
            parts.append(f"{self.path}: ")
        parts.append(self.what)
        if self.fix:
            parts.append(f" (fix: {self.fix})")
        return "".join(parts).replace("\n", " ")
