"""``omnirecon pet``: parameter-efficient tuning of Omni-Recon's appearance branch on lifted semantics.

Per scene: ``--labelled`` evenly spaced pool views carry ground-truth labels; the model is tuned
(:mod:`omnirecon.lift.tune`: LoRA, bias-only or the full appearance branch) on the leave-one-out lift
of their labels, and the mIoU of their labels lifted into the held-out targets is measured before
and after. Writes ``pet.json`` (mIoU before/after, tuned parameters, mIoU gained per parameter, the
loss curve) and ``<scene>/adapters.safetensors``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from omnirecon.data.io import write_json
from omnirecon.engine.machine import CheckpointInput, ThreadsConfig, load_model, set_threads
from omnirecon.engine.protocols import targets_and_pool
from omnirecon.engine.scenes import prepare_scenes
from omnirecon.errors import InputError
from omnirecon.lift import tune as T
from omnirecon.lift.predictors import class_table
from omnirecon.lift.tune import PETOptions
from omnirecon.models.omnirecon import OmniRecon
from omnirecon.options import OutFolder, SynthEvalScenes, check_options
from omnirecon.provenance import provenance
from omnirecon.workflows.folder import FolderVerb


@dataclass
class PETConfig(SynthEvalScenes, OutFolder, CheckpointInput, ThreadsConfig, FolderVerb):
    """Tune LoRA adapters or biases of Omni-Recon's appearance branch with a semantic cross-entropy on a
    few labelled views (leave-one-out lifting); mIoU of lifted labels on held-out targets before/after."""

    labelled: int = 6
    """Labelled views per scene (evenly spaced over the protocol's pool)."""
    options: PETOptions = field(default_factory=PETOptions)
    """Tuning settings (mode, rank, steps, ...)."""

    command: ClassVar[str] = "pet"

    def default_out(self) -> Path:
        return Path("outputs/pet") / f"{Path(self.ckpt).name}_{self.options.mode}"

    def run(self, folder: Path | None = None) -> list[str]:
        lines: list[str] = []
        import copy

        o = self.options
        check_options("pet", self)  # the numbers, --options.* too (omnirecon/options.py); for callers other than the CLI
        set_threads(self.threads)
        base, info = load_model(self.ckpt, None, "cpu")
        if not isinstance(base, OmniRecon):
            raise InputError(f"PET tunes Omni-Recon's decoupled appearance branch, got {info['name']}", self.ckpt,
                             "use an omnirecon checkpoint")
        out = self.out or self.default_out()
        folder = folder or out
        scenes = prepare_scenes([self.scene], self.synth_count, self.cache, protocol_set=self.protocol_set)
        rows = []
        for es in scenes:
            if es.scene.labels is None:
                raise InputError("the scene has no label maps", es.path, "use a procedural scene (synth:eval)")
            rows.append(run_pet(copy.deepcopy(base), es, o, self.labelled, folder / es.name))
        gain = float(np.mean([r["after"]["miou"] - r["before"]["miou"] for r in rows]))
        result = {"provenance": provenance(seed=o.seed), "model": info, "options": asdict(o), "labelled": self.labelled,
                  "scenes": rows, "mean_gain_miou": gain, "params": rows[0]["params"],
                  "gain_per_param": gain / max(rows[0]["params"], 1)}
        write_json(folder / "pet.json", result)
        for r in rows:
            lines.append(f"{r['scene']}: mIoU {r['before']['miou']:.2f} -> {r['after']['miou']:.2f} "
                  f"({o.mode}, {r['params']} tuned parameters, {o.steps} steps)")
        lines.append(f"mean gain {gain:+.2f} mIoU, {1000 * result['gain_per_param']:+.3f} mIoU per 1k tuned parameters; "
              f"wrote {out / 'pet.json'}")
        return lines


def run_pet(model, es, options: PETOptions, labelled_count: int, folder: Path) -> dict:
    """Tune ``model`` (a copy) on one scene; returns its JSON row and saves the adapters."""

    scene = es.scene
    targets, pool = targets_and_pool(es.protocol, scene)
    if len(pool) < labelled_count:
        raise InputError(f"the pool has {len(pool)} views, fewer than --labelled {labelled_count}", es.path,
                         "lower --labelled")
    labelled = [pool[i] for i in np.unique(np.linspace(0, len(pool) - 1, labelled_count).round().astype(int))]
    table = class_table(scene)
    K = min(options.num_views, len(labelled) - 1)
    views = T.labelled_views(model, scene, labelled, table, K)
    before = T.lifted_miou(model, scene, targets, labelled, table, K)
    fit = T.tune(model, views, options)
    after = T.lifted_miou(model, scene, targets, labelled, table, K)
    T.save_adapters(model, folder / "adapters.safetensors", options)
    return {"scene": es.name, "targets": targets, "labelled": labelled, "before": before, "after": after,
            "params": fit["params"], "losses": fit["losses"], "adapters": str(folder / "adapters.safetensors")}
