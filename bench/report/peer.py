"""BENCHMARKS.md section: IBRNet reference vs ibrnet-paper (`python -m bench peer_ibrnet`)."""

from __future__ import annotations

import json
from pathlib import Path

from bench.report.common import prov


def section(results: Path) -> str | None:
    parts = [text for text in (_same_config(results), _eval_config(results), _train_config(results)) if text]
    return "\n\n".join(parts) if parts else None


def _same_config(results: Path) -> str | None:
    f = results / "peer_ibrnet.json"
    if not f.is_file():
        return None
    r = json.loads(f.read_text())
    c = r["config"]
    lines = ["## IBRNet reference vs ibrnet-paper (`python -m bench peer_ibrnet`)", "",
             f"Same configuration on both sides: {c['views']} source views of {c['width']}x{c['height']}, "
             f"{c['samples']} samples, inverse depth, chunk {c['chunk']}, {c['train_rays']} rays per training "
             f"step, random weights, one thread, each side in its own process ({c['rounds']} alternating "
             "round(s), best time and largest peak RSS kept). The reference is the official code "
             f"({c.get('peer_config', 'its layout')}), its CUDA calls mapped to the CPU.", ""]
    if r.get("peer_note"):
        lines += [f"**Reference not measured: {r['peer_note']}.** Run `python -m bench peer_ibrnet --ibrnet-root "
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
    return "\n".join([*lines, "", prov(r["provenance"])])


def _eval_config(results: Path) -> str | None:
    """A ``--crop`` run at the reference's evaluation configuration (render only): each side's encoder and window
    CPU seconds, the full view projected from them, and the ratios to the reference."""
    f = results / "peer_ibrnet_eval.json"
    if not f.is_file():
        return None
    r = json.loads(f.read_text())
    c, q = r["config"], r.get("ratios") or {}
    cw, ch = c["crop"]
    lines = ["## IBRNet reference vs ibrnet-paper at the reference's evaluation configuration "
             "(`python -m bench peer_ibrnet --crop`)", "",
             f"IBRNet's LLFF evaluation: {c['views']} source views of {c['width']}x{c['height']} (fern at factor 4), "
             f"{c['samples']} samples, inverse depth, chunk {c['chunk']}, random weights, one thread, each side in its "
             f"own process. To fit the shared CPU, each side encodes all {c['views']} sources and renders a centred "
             f"{cw}x{ch} window of the target; the full view's CPU seconds are projected as encode + (window - encode) "
             f"x {c['width'] * c['height']} / {cw * ch} rays (every ray costs the same). "
             + ("Render only: the reference's training step at this configuration was killed by the kernel's OOM "
                "killer at 11 GB resident on this shared machine." if not c["train_steps"] else ""), "",
             "| side | switches | encode CPU s | window CPU s | rays/CPU-s past the encoder | full view CPU s "
             "(projected) | render peak RSS (MB) | render × ref. | peak RSS / ref. | PSNR to our twin (dB) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, b in r["best"].items():
        ratio = q.get(name) or {}
        psnr = b.get("psnr_to_reference_db", "–")
        lines.append(f"| {name} | {b.get('switches') if name != 'peer' else 'official code'} | {b['encode_cpu_s']} | "
                     f"{b['render_cpu_s']} | {b['render_rays_per_s']} | {b['full_view_cpu_s']} | "
                     f"{b['render_peak_rss_mb']} | {ratio.get('render_speedup', '–')}× | "
                     f"{ratio.get('render_peak_rss_ratio', '–')} | {'identical' if psnr is None else psnr} |")
    lines += ["", "The window is smaller than the reference's chunk, so its peak RSS is below a full view's: the RSS "
              f"ratio favours the reference. Ratios of process CPU seconds from this one run, one round; load average "
              f"at the start {r.get('loadavg_start')}, at the end {r.get('loadavg_end')}."]
    return "\n".join([*lines, "", prov(r["provenance"])])


def _train_config(results: Path) -> str | None:
    """A run at the reference's training configuration (``peer_ibrnet_train.json``): training steps side by side,
    the render of a small window for the encoder's cost."""
    f = results / "peer_ibrnet_train.json"
    if not f.is_file():
        return None
    r = json.loads(f.read_text())
    c, q = r["config"], r.get("ratios") or {}
    official = (c["views"], c["width"], c["height"]) == (10, 600, 400)
    lines = ["## IBRNet reference vs ibrnet-paper: training (`python -m bench peer_ibrnet --views 10 --train-rays 500`)", "",
             "IBRNet's own training configuration is 10 source views of its 400x600 random crop of LLFF, 500 rays per "
             "step (N_rand), 64 + 64 samples. "
             + ("This run is at it. " if official else
                f"There, the reference's process passed the 6 GB this shared machine allows one job (stopped at 6045 MB "
                f"resident), so this run is the largest that fit: {c['views']} source views of {c['width']}x{c['height']}. ")
             + f"A step as its `train.py` takes it: {c['train_rays']} rays, the encoder on every source with gradients, "
             "masked MSE on both passes, backward, optimizer step; random weights, one thread, each side in its own "
             f"process, {c['train_steps']} timed step(s) after a warm-up (best kept). Peak RSS is the whole process's "
             "(a render of a small window comes first).", "",
             "| side | switches | train CPU s/step (wall) | train rays/CPU-s | peak RSS (MB) | train × ref. | "
             "peak RSS / ref. |", "|---|---|---|---|---|---|---|"]
    for name, b in r["best"].items():
        ratio = q.get(name) or {}
        lines.append(f"| {name} | {b.get('switches') if name != 'peer' else 'official code'} | "
                     f"{b['train_step_cpu_s']} ({b['train_step_s']}) | {b['train_rays_per_s']} | {b['peak_rss_mb']} | "
                     f"{ratio.get('train_speedup', '–')}× | {ratio.get('peak_rss_ratio', '–')} |")
    lines += ["", f"Ratios of process CPU seconds from this one run; load average at the start {r.get('loadavg_start')}, "
              f"at the end {r.get('loadavg_end')}."]
    return "\n".join([*lines, "", prov(r["provenance"])])

