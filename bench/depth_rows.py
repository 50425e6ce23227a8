"""Where ``python -m bench depth_sources`` keeps each row's mesh and finetune record, for the benches that read them
(``realtime_blend``, ``viewer_parity``)."""

from __future__ import annotations

import argparse
from pathlib import Path

WORK = Path(__file__).resolve().parents[1] / "outputs" / "bench" / "depth_sources"
"""Each row's folder (``<scene>_<source slug>``: its mesh and finetune record)."""


def row_arguments(p: argparse.ArgumentParser, rows: dict) -> None:
    """``--scenes`` (keys of ``rows``: the depth_sources row each scene reads) and ``--meshes`` (where the rows'
    folders are)."""
    p.add_argument("--scenes", nargs="+", default=list(rows), choices=list(rows))
    p.add_argument("--meshes", type=Path, default=WORK, help="where the depth_sources rows' folders are")
