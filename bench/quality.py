"""Novel-view quality of the shipped tiny checkpoints and the non-learned floor.

    python -m bench quality                         # floor and the shipped tiny checkpoints, every evaluation scene
    python -m bench quality --models floor --tiny   # a fast subset (tests)
    python -m bench quality --protocol-set cpu256 --ks 3                  # the real scenes at a 256-px long side
    python -m bench quality --protocol-set cpu256 --guided --scenes fern  # the same, surface-guided

Held-out procedural scenes (``synth:eval``, seeds 900000+) and the real scenes dtu_scan24,
dtu_scan37, fern (never trained on), fox and lego (training scenes: fitting, not generalisation),
with 3 and 10 source views, under the ``cpu`` protocol set of ``omnirecon.engine.evaluate`` (64 px long side,
fewer targets; docs/evaluation.md). Writes ``bench/results/quality_<model>.json``.

A run for some scenes or Ks merges its rows into the results file it writes (:func:`merge`): the rows it scored
replace theirs, the others stay, each row with the provenance of the run that scored it. A file measured with
another checkpoint, protocol set, sampling or overrides is replaced instead (the run says so).

``--protocol-set cpu256``: the real scenes only, at a 256-px long side with 2 targets per scene, scored twice: under
their protocols (``cpu256``) and on the test views of the extrapolation split (``cpu256-extrapolation``: views just
beyond those the sources are drawn from). Writes ``quality_<set>[_guided]_<model>.json`` per set.
"""

from __future__ import annotations

import argparse
import copy
import json
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


def load(model_name: str, long_side: int | None = None):
    """The model and its provenance record (``floor``: the plane-sweep floor); ``long_side``: the weights of the
    checkpoint trained nearest that size (px; ``omnirecon.engine.checkpoint.folder_for_size``)."""
    from omnirecon.engine.checkpoint import fingerprint, folder_for_size, load_checkpoint
    from omnirecon.models.registry import build_model

    if model_name == "floor":
        return build_model("floor"), {"name": "floor", "preset": "floor"}
    ckpt = folder_for_size(ROOT / "checkpoints" / model_name, long_side)
    model, meta = load_checkpoint(ckpt)
    return model, {"name": model_name, "preset": meta["preset"], "checkpoint": str(ckpt.relative_to(ROOT)),
                   "step": meta["step"], "cpu_seconds": meta["extra"].get("cpu_s"), "sha256": fingerprint(ckpt)["sha256"]}


def run(model_name: str, out_dir: Path, tiny: bool, threads: int, protocol_set: str = "cpu", guided: bool = False,
        ks: tuple[int, ...] | None = None, only: list[str] | None = None, guided_options: dict | None = None) -> dict:
    """Score ``model_name`` under every set of ``SETS[protocol_set]``, each merged into its results file (:func:`save`);
    returns the last set's file. ``guided_options``: ``GuidedOptions`` fields over the family defaults (``guided``).
    The weights: those ``eval`` loads (trained nearest the set's size, full path or guided)."""
    from omnirecon.engine.evaluate import evaluate
    from omnirecon.engine.protocols import set_long_side
    from omnirecon.models.guided import GuidedOptions

    torch.set_num_threads(threads)
    model, info = load(model_name, set_long_side(SETS[protocol_set][0]))
    ks = ks or ((3,) if tiny else (3, 10))
    for pset in SETS[protocol_set]:
        name = result_name(pset, model_name, guided)
        result = evaluate(model, scenes(tiny, protocol_set, only), ks, ROOT / "outputs" / "bench" / f"eval_{name[8:-5]}",
                          model_info=info, synth_count=1 if tiny else 10, protocol_set=pset,
                          max_targets=1 if tiny else None, cache=ROOT / "outputs" / "cache", progress=not tiny,
                          guided=GuidedOptions(on=True, **(guided_options or {})) if guided and model_name != "floor"
                          else None)
        result = save(out_dir / name, result)
    return result


def incompatible(old: dict, new: dict) -> str | None:
    """Why ``old``'s rows cannot stand beside ``new``'s in one results file (None: they can): another checkpoint,
    protocol set, sampling (``guided``), geometry, overrides of the protocols or definition of a shared protocol."""
    old, new = json.loads(json.dumps(old)), json.loads(json.dumps(new))  # as the file holds them (tuples: lists)
    for what, a, b in (("checkpoint", old["model"].get("sha256"), new["model"].get("sha256")),
                       ("model", old["model"].get("name"), new["model"].get("name")),
                       ("protocol set", old.get("protocol_set"), new.get("protocol_set")),
                       ("guided options", old.get("guided"), new.get("guided")),
                       ("geometry", old.get("geometry"), new.get("geometry")),
                       ("overrides", old.get("non_protocol"), new.get("non_protocol")),
                       *((f"protocol {p}", old["protocols"][p], new["protocols"][p])
                         for p in old.get("protocols", {}) if p in new.get("protocols", {}))):
        if a != b:
            return f"its rows were measured with {what} {a!r}, this run with {b!r}"
    return None


def merge(old: dict | None, new: dict) -> dict:
    """``new`` (one run's results) merged into ``old`` (the results file before it, None: none).

    A row is one (scene, K): ``new``'s rows replace ``old``'s, ``old``'s other rows stay. Each row keeps the
    provenance of the run that scored it in ``settings[K]["provenance"]`` (a row of a file written before rows
    carried one takes that file's); the file's ``provenance`` is the latest run's. The per-protocol means and
    ``seconds_per_view`` are recomputed over the merged rows. Call only when :func:`incompatible` says None."""
    from omnirecon.engine.eval_report import protocol_means

    def stamped(result: dict) -> dict:
        result = copy.deepcopy(result)
        for sc in result["scenes"]:
            for row in sc["settings"].values():
                row.setdefault("provenance", result["provenance"])
        return result

    new = stamped(new)
    if old is None:
        return new
    scenes = {sc["name"]: sc for sc in stamped(old)["scenes"]}
    for sc in new["scenes"]:
        kept = scenes.get(sc["name"], {"settings": {}, "skipped": {}})
        settings = kept["settings"] | sc["settings"]
        skipped = {k: v for k, v in (kept.get("skipped", {}) | sc.get("skipped", {})).items() if k not in settings}
        scenes[sc["name"]] = sc | {"settings": dict(sorted(settings.items(), key=lambda kv: int(kv[0]))),
                                   "skipped": skipped}
    records = list(scenes.values())
    ks = sorted({int(k) for sc in records for k in sc["settings"]})
    seconds = [v["seconds"] for sc in records for row in sc["settings"].values() for v in row["views"]]
    return new | {"protocols": old.get("protocols", {}) | new.get("protocols", {}), "num_views": ks,
                  "scenes": records, "means": protocol_means(records, ks),
                  "seconds_per_view": sum(seconds) / len(seconds) if seconds else None}


def save(path: Path, result: dict) -> dict:
    """Write ``result`` to ``path`` merged into the results already there (:func:`merge`); returns what it wrote."""
    old = json.loads(path.read_text()) if path.is_file() else None
    why = incompatible(old, result) if old is not None else None
    if why:
        print(f"{path.name}: {why}; its earlier rows are dropped")
    merged = merge(None if why else old, result)
    write_json(path, merged)
    return merged


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
    p.add_argument("--guided-options", type=json.loads, default=None,
                   help='with --guided: GuidedOptions fields over the family defaults, a JSON object, e.g. '
                        '\'{"prior_scale": 8}\' (recorded with the results; use another --out to keep the defaults\' file)')
    p.add_argument("--ks", type=int, nargs="+", default=None, help="source-view counts (default: 3 and 10)")
    p.add_argument("--scenes", nargs="+", default=None, help="only these real scenes (fern, dtu_scan24, ...)")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    a = p.parse_args(argv)
    for m in a.models:
        r = run(m, a.out, a.tiny, a.threads, a.protocol_set, a.guided, tuple(a.ks) if a.ks else None, a.scenes,
                a.guided_options)
        print(m, {proto: {k: round(v.get("psnr", float("nan")), 2) for k, v in ks.items()} for proto, ks in r["means"].items()})
