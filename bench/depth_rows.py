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


MESH_VARIANTS = ("sky kept", "all views", "coherent")
"""Variants of a depth_sources row that change its mesh (besides ``match N``): they key the meshes a run shares."""


def mesh_settings(variant: str) -> dict:
    """``MeshOptions`` settings of a row's variants: ``sky kept`` (no depth dropped where the photo shows the known
    background colour), ``match N`` (stereo matched at a long side of N px), ``coherent`` (the coherent surface,
    ``omnirecon/mesh/surface.py``, instead of fusion and completion)."""
    from omnirecon.mesh.stereo import StereoOptions

    parts = variant.split(", ")
    out: dict = {"drop_background": False} if "sky kept" in parts else {}
    match = [int(v.split()[1]) for v in parts if v.startswith("match ")]
    if match:
        out["stereo"] = StereoOptions(match_side=match[0])
    if "coherent" in parts:
        out["surface"] = "coherent"
    return out
