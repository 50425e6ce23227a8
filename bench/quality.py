"""Novel-view quality of the shipped tiny checkpoints and the non-learned floor.

    python -m bench quality                         # floor and the shipped tiny checkpoints, every evaluation scene
    python -m bench quality --models floor --tiny   # a fast subset (tests)
    python -m bench quality --protocol-set cpu256 --ks 3                  # the real scenes at a 256-px long side
    python -m bench quality --protocol-set cpu256 --guided --scenes fern  # the same, surface-guided

Held-out procedural scenes (``synth:eval``, seeds 900000+) and the real scenes dtu_scan24,
dtu_scan37, fern (never trained on), fox and lego (training scenes: fitting, not generalisation),
with 3 and 10 source views, under the ``cpu`` protocol set of ``omnirecon.engine.evaluate`` (64 px long side,
fewer targets; docs/evaluation.md). Writes ``bench/results/quality_<model>.json``.

``--protocol-set cpu256``: the real scenes only, at a 256-px long side with 2 targets per scene, scored twice: under
their protocols (``cpu256``) and on the test views of the extrapolation split (``cpu256-extrapolation``: views just
beyond those the sources are drawn from). Writes ``quality_<set>[_guided]_<model>.json`` per set.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from omnirecon.data.io import write_json

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
REAL = ["neus_dtu/dtu_scan24", "neus_dtu/dtu_scan37", "llff/fern", "instant_ngp/fox", "blender/lego"]
SETS = {"cpu": ("cpu",), "cpu256": ("cpu256", "cpu256-extrapolation"), "cpu256-extrapolation": ("cpu256-extrapolation",)}
"""``--protocol-set`` -> the protocol sets it scores (one results file each)."""


def scenes(tiny: bool, protocol_set: str = "cpu", only: list[str] | None = None) -> list[str]:
    if tiny:
        return ["synth:eval"]
    real = [str(SHARED / r) for r in REAL if (SHARED / r).is_dir() and (not only or Path(r).name in only)]
    return real if protocol_set != "cpu" else ["synth:eval", *real]


def result_name(protocol_set: str, model_name: str, guided: bool = False) -> str:
    """``quality_<model>.json`` for the ``cpu`` set, ``quality_<set>[_guided]_<model>.json`` otherwise."""
    if protocol_set == "cpu" and not guided:
        return f"quality_{model_name}.json"
    return f"quality_{protocol_set}{'_guided' if guided else ''}_{model_name}.json"


def load(model_name: str):
    """The model and its provenance record (``floor``: the plane-sweep floor)."""
    from omnirecon.engine.checkpoint import fingerprint, load_checkpoint
    from omnirecon.models.registry import build_model

    if model_name == "floor":
        return build_model("floor"), {"name": "floor", "preset": "floor"}
    ckpt = ROOT / "checkpoints" / model_name
    model, meta = load_checkpoint(ckpt)
    return model, {"name": model_name, "preset": meta["preset"], "checkpoint": str(ckpt.relative_to(ROOT)),
                   "step": meta["step"], "cpu_seconds": meta["extra"].get("cpu_s"), "sha256": fingerprint(ckpt)["sha256"]}


def run(model_name: str, out_dir: Path, tiny: bool, threads: int, protocol_set: str = "cpu", guided: bool = False,
        ks: tuple[int, ...] | None = None, only: list[str] | None = None) -> dict:
    """Score ``model_name`` under every set of ``SETS[protocol_set]``; returns the last set's results."""
    from omnirecon.engine.evaluate import evaluate
    from omnirecon.models.guided import GuidedOptions

    torch.set_num_threads(threads)
    model, info = load(model_name)
    ks = ks or ((3,) if tiny else (3, 10))
    for pset in SETS[protocol_set]:
        name = result_name(pset, model_name, guided)
        result = evaluate(model, scenes(tiny, protocol_set, only), ks, ROOT / "outputs" / "bench" / f"eval_{name[8:-5]}",
                          model_info=info, synth_count=1 if tiny else 10, protocol_set=pset,
                          max_targets=1 if tiny else None, cache=ROOT / "outputs" / "cache", progress=not tiny,
                          guided=GuidedOptions(on=True) if guided and model_name != "floor" else None)
        write_json(out_dir / name, result)
    return result


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", nargs="+", default=["floor", "gpnr-tiny", "ibrnet-tiny", "omnirecon-tiny"])
    p.add_argument("--tiny", action="store_true", help="one procedural scene, one target, K=3 (tests)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--protocol-set", choices=list(SETS), default="cpu",
                   help="cpu: 64-px long side, procedural and real scenes; cpu256: the real scenes at a 256-px long "
                        "side, under their protocols and on the extrapolation split's test views; "
                        "cpu256-extrapolation: only the latter")
    p.add_argument("--guided", action="store_true", help="render the targets surface-guided (--guided.on)")
    p.add_argument("--ks", type=int, nargs="+", default=None, help="source-view counts (default: 3 and 10)")
    p.add_argument("--scenes", nargs="+", default=None, help="only these real scenes (fern, dtu_scan24, ...)")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    for m in a.models:
        r = run(m, a.out, a.tiny, a.threads, a.protocol_set, a.guided, tuple(a.ks) if a.ks else None, a.scenes)
        print(m, {proto: {k: round(v.get("psnr", float("nan")), 2) for k, v in ks.items()} for proto, ks in r["means"].items()})
