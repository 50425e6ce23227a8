"""``omnirecon synth``: generate a batch of procedural scenes in parallel."""

from __future__ import annotations

import multiprocessing
import os
import shutil
import signal
import time
from dataclasses import dataclass, fields
from pathlib import Path

from omnirecon.data.synth.generate import SynthOptions, generate_scene, scene_name
from omnirecon.errors import InputError
from omnirecon.options import OutPath, Overwrites, Seeded, check_options, command_defaults
from omnirecon.progress import progress_bar


@dataclass
@command_defaults(out=Path("outputs/synth"))
class SynthConfig(OutPath, Overwrites, Seeded, SynthOptions):
    """Generate procedural scenes of textured primitives with exact ground truth (depth, normals,
    labels, masks, mesh) in the Blender/NeRF-synthetic layout. Scene i uses seed ``seed + i``; the
    same seed always gives byte-identical files."""

    num_scenes: int = 1
    """How many scenes to generate."""
    workers: int | None = None
    """Parallel processes (default: all CPU cores)."""
    def check(self) -> None:
        check_options("synth", self)  # the numbers (omnirecon/options.py); here for callers other than the CLI
        super().check()
        if self.out.exists() and not self.out.is_dir():
            raise InputError("output path exists and is not a folder", self.out, "pass a folder for --out")

    def options(self) -> SynthOptions:
        return SynthOptions(**{f.name: getattr(self, f.name) for f in fields(SynthOptions)})


def _init_worker() -> None:
    """Worker set-up: one torch thread, and Ctrl-C handled by the parent alone."""
    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(1)


def _one(task: tuple[Path, int, SynthOptions, bool]) -> int:
    out, seed, options, overwrite = task
    generate_scene(out, seed, options, overwrite)
    return seed


def run_batch(cfg: SynthConfig, quiet: bool = True) -> dict:
    """Generate ``cfg.num_scenes`` scenes; returns timing numbers (seconds, scenes, views, workers).

    On Ctrl-C or an error the workers are stopped at once and their unfinished (temporary) scene
    folders removed; finished scenes stay, so running the same command again resumes.
    """

    cfg.out.mkdir(parents=True, exist_ok=True)
    options = cfg.options()
    seeds = [cfg.seed + i for i in range(cfg.num_scenes)]
    todo = [s for s in seeds if cfg.overwrite or not (cfg.out / scene_name(s)).exists()]
    workers = min(cfg.workers or os.cpu_count() or 1, max(len(todo), 1))
    tasks = [(cfg.out, s, options, cfg.overwrite) for s in todo]
    start = time.perf_counter()
    with progress_bar("synth", "scenes", disable=quiet) as progress:
        task = progress.add_task("synth", total=len(todo))
        if workers == 1:
            torch_threads = _torch_threads(1)
            try:
                for t in tasks:
                    _one(t)
                    progress.advance(task)
            finally:
                _torch_threads(torch_threads)
        else:
            pool = multiprocessing.get_context("spawn").Pool(workers, initializer=_init_worker)
            try:
                for _ in pool.imap_unordered(_one, tasks):
                    progress.advance(task)
                pool.close()
            except BaseException:
                pool.terminate()  # killed mid-scene: only hidden temporary folders are left ...
                pool.join()
                for s in todo:  # ... and removed here
                    for tmp in cfg.out.glob(f".{scene_name(s)}.tmp*"):
                        shutil.rmtree(tmp, ignore_errors=True)
                raise
            pool.join()
    seconds = time.perf_counter() - start
    result = {"seconds": seconds, "scenes": len(todo), "skipped": len(seeds) - len(todo),
              "views": len(todo) * cfg.views, "workers": workers}
    if not quiet:
        per_view = 1000 * seconds / max(result["views"], 1)
        print(f"wrote {len(todo)} scenes to {cfg.out} in {seconds:.1f} s ({per_view:.1f} ms per view, "
              f"{workers} workers)" + (f"; kept {result['skipped']} existing" if result["skipped"] else ""))
    return result


def _torch_threads(n: int) -> int:
    """Set torch's thread count; returns the previous one."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    return previous
