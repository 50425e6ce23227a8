"""Mesh-path vs volumetric FPS for BENCHMARKS.md: ``omnirecon bench`` writing ``bench/results/mesh_fps.json``.

    python -m bench mesh_fps --threads 2     # every option: omnirecon/engine/speed.py (BenchConfig)

The issue's goals (>= 30 FPS at 504x378, >= 60 FPS at 336x252 on 2 cores, tuned model), on a quiet machine
(2 threads measured beside other jobs are meaningless: check the load average in the JSON)::

    python -m bench mesh_fps --size 504 378 --threads 2 --ckpt TUNED/checkpoint --out /tmp/fps_504.json
    python -m bench mesh_fps --size 336 252 --threads 2 --ckpt TUNED/checkpoint --out /tmp/fps_336.json

(``TUNED``: e.g. ``omnirecon finetune ... --save --out TUNED``; ``--threads 1`` for the one-core numbers.)
"""

from pathlib import Path


def main(argv: list[str] | None = None) -> None:
    import tyro

    from omnirecon.engine.speed import BenchConfig, measure

    measure(tyro.cli(BenchConfig, args=argv, default=BenchConfig(out=Path(__file__).parent / "results" / "mesh_fps.json")))
