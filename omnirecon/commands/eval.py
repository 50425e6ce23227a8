"""``omnirecon eval``: score a model on held-out views under one fixed protocol per dataset."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from omnirecon.engine.evaluate import evaluate
from omnirecon.engine.machine import (
    GuidedRendering,
    MachineConfig,
    ModelChoice,
    load_model,
    pick_device,
    set_threads,
)
from omnirecon.engine.protocols import SYNTH_PREFIX, set_long_side
from omnirecon.options import OutFolder, SceneCache, SynthCount, command_defaults
from omnirecon.outputs import claim


def default_name(ckpt: Path | None, model_name: str) -> str:
    """Output name: ``<run>_<checkpoint>`` for ``.../<run>/checkpoints/<checkpoint>``, else the folder or model name."""
    if ckpt is None:
        return model_name
    ckpt = Path(ckpt).resolve()
    return f"{ckpt.parent.parent.name}_{ckpt.name}" if ckpt.parent.name == "checkpoints" else ckpt.name


@dataclass
@command_defaults(synth_count=10)
class EvalCommand(GuidedRendering, SceneCache, SynthCount, OutFolder, ModelChoice, MachineConfig):
    """Evaluate a checkpoint (or the non-learned plane-sweep floor) on held-out views: PSNR, SSIM,
    ST-LPIPS (and LPIPS where its weights are on the machine), per scene and averaged, under the
    fixed protocols of docs/evaluation.md. Writes results.json, results.md and one
    GT | render | error panel per target view."""

    scenes: tuple[str, ...] = (SYNTH_PREFIX,)
    """Scene folders (any supported format) and/or synth:eval[:object|frontal|forward] (the held-out
    procedural set, generated on first use)."""
    num_views: tuple[int, ...] = (3, 10)
    """Source-view counts K to evaluate (3 and 10 are the standard settings)."""
    max_targets: int | None = None
    """Score at most this many targets per scene instead of the protocol's choice (quick checks;
    results are marked as not following the protocol)."""
    save_images: bool = True
    """Write a GT | render | |error| panel per target."""
    protocol_set: Literal["full", "cpu", "cpu256", "cpu256-extrapolation"] = "full"
    """``full``: the published protocols (128 px); ``cpu``: the same rules at 64 px with fewer targets
    (the CPU benchmark of the tiny presets; not comparable with ``full``); ``cpu256``: at 256 px, 2 targets per
    scene; ``cpu256-extrapolation``: ``cpu256`` scored on the extrapolation split's test views."""
    geometry: bool = False
    """Also extract a mesh per scene and K (`omnirecon mesh`'s protocol; sources: DTU's 23 24 33 or K
    evenly spaced pool views) and score it: Chamfer / F-score against a procedural scene's exact
    mesh, silhouette IoU on the targets' masks. Per-target depth errors need no flag."""

    def main(self) -> None:
        out = self.out or Path("outputs/eval") / default_name(self.ckpt, self.model or "model")
        # The output set is built beside --out and swapped in whole (see outputs.claim).
        self.guided.check()
        with claim(out, "eval", inputs=(self.ckpt, *self.scenes), mode="replace") as c:
            set_threads(self.threads)
            device = pick_device(self.device)
            net, info = load_model(self.ckpt, self.model, device,
                                   long_side=set_long_side(self.protocol_set))
            result = evaluate(net, list(self.scenes), self.num_views, c.work, model_info=info, chunk=self.chunk,
                              device=device, max_targets=self.max_targets, synth_count=self.synth_count,
                              cache=self.cache, save_images=self.save_images, protocol_set=self.protocol_set,
                              geometry=self.geometry, guided=self.guided)
        from omnirecon.engine.eval_report import summary_lines  # lazy: the report module loads only after a run

        for line in summary_lines(result):
            print(line)
        print(f"wrote {out / 'results.json'} and {out / 'results.md'}")
