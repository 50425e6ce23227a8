"""Mesh-path vs volumetric FPS for BENCHMARKS.md: ``omnirecon bench`` writing ``bench/results/mesh_fps.json``.

    python -m bench mesh_fps --threads 2     # every option: omnirecon/engine/speed.py (BenchConfig)
"""

from pathlib import Path


def main(argv: list[str] | None = None) -> None:
    import tyro

    from omnirecon.engine.speed import BenchConfig, measure

    measure(tyro.cli(BenchConfig, args=argv, default=BenchConfig(out=Path(__file__).parent / "results" / "mesh_fps.json")))
