"""Mesh-path vs volumetric FPS for BENCHMARKS.md: ``omnirecon bench`` writing ``bench/results/mesh_fps.json``.

    python bench/mesh_fps.py --threads 2     # every option: omnirecon/engine/speed.py (BenchConfig)
"""

from pathlib import Path

import tyro

from omnirecon.engine.speed import BenchConfig, measure

if __name__ == "__main__":
    measure(tyro.cli(BenchConfig, default=BenchConfig(out=Path(__file__).parent / "results" / "mesh_fps.json")))
