"""``omnirecon doctor``: what works on this machine, what falls back, and how to fix it."""

from __future__ import annotations

import json
from dataclasses import dataclass

from omnirecon.workflows.doctor import run_checks


@dataclass
class DoctorCommand:
    """Check torch and CUDA, EGL rasterization, Chromium, video, metrics and optional extras, and print
    what works and what falls back, as a table."""

    json: bool = False
    """Print the checks as JSON instead of a table."""

    def main(self) -> None:
        rows = run_checks()
        if self.json:
            print(json.dumps([r.__dict__ for r in rows], indent=1))
            return
        from rich.console import Console
        from rich.table import Table

        table = Table(title="omnirecon doctor")
        for col in ("component", "status", "detail", "without it"):
            table.add_column(col, overflow="fold")
        colour = {"ok": "green", "fallback": "yellow", "missing": "red"}
        for r in rows:
            table.add_row(r.name, f"[{colour[r.status]}]{r.status}[/]", r.detail, r.consequence)
        Console().print(table)
