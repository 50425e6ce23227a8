"""Records written in an output folder name the paths inside it relative to it: a run builds its output in a
temporary folder that is renamed into place at the end (:func:`omnirecon.outputs.claim`), so a record must not
name the temporary folder. :func:`relative_to` rewrites a JSON-like value, :func:`relative_records` every JSON
file under a folder."""

from __future__ import annotations

import json
import os
from pathlib import Path


def real(path: Path) -> Path:
    """``path`` absolute with every existing link resolved (the same folder reached two ways compares equal)."""
    return Path(os.path.realpath(os.path.abspath(path)))


def relative_to(value, folder: Path):
    """``value`` (JSON-like) with every string naming ``folder`` or a path inside it made relative to
    ``folder`` (``"."`` for the folder itself); other strings unchanged."""
    prefixes = sorted({str(folder), str(Path(folder).absolute()), str(real(folder))}, key=len, reverse=True)

    def fix(v):
        if isinstance(v, str):
            for p in prefixes:
                if v == p:
                    return "."
                if v.startswith(p + os.sep):
                    return v[len(p) + 1:]
            return v
        if isinstance(v, list):
            return [fix(x) for x in v]
        if isinstance(v, dict):
            return {k: fix(x) for k, x in v.items()}
        return v

    return fix(value)


def relative_records(folder: Path) -> list[Path]:
    """Apply :func:`relative_to` to every JSON file under ``folder`` (rewritten atomically); returns those
    changed. Files that are not JSON are left alone."""
    changed = []
    for f in sorted(Path(folder).rglob("*.json")):
        try:
            data = json.loads(f.read_text())
        except (OSError, ValueError):
            continue
        new = relative_to(data, folder)
        if new != data:
            tmp = f.parent / f".{f.stem}.pid{os.getpid()}.json"
            tmp.write_text(json.dumps(new, indent=1))
            os.replace(tmp, f)
            changed.append(f)
    return changed
