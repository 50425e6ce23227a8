"""Mesh-path vs volumetric FPS for BENCHMARKS.md: ``omnirecon bench`` writing ``bench/results/mesh_fps.json``.

    python bench/mesh_fps.py --threads 2     # see omnirecon/speed.py for every option
"""

import sys
from pathlib import Path

from omnirecon.speed import main

if __name__ == "__main__":
    argv = sys.argv[1:]
    if "--out" not in argv:
        argv += ["--out", str(Path(__file__).parent / "results" / "mesh_fps.json")]
    main(argv)
