"""BENCHMARKS.md section: real training objects on black or random backgrounds (`python -m bench train_background`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import prov, read

GROUPS = {"real": "mean: real scenes, held-out views", "black": "mean: lego and chair on black",
          "validation": "mean: every real validation row", "procedural": "mean: procedural validation seeds"}


def cell(r: dict, control: dict | None, value, key) -> str:
    """PSNR, with the difference to the control in brackets (arms other than the control)."""
    if value is None:
        return "-"
    if control is None or r is control:
        return f"{value:.2f}"
    return f"{value:.2f} ({value - control[key]:+.2f})"


def probe_columns(results: Path, name: str, control: str, control_first: bool = False):
    """``(results, probes by budget, columns)`` of an arms-against-a-control results file, None before a run; a
    column per ``(budget, arm, its results, the control's results)``, with ``control_first`` the control's first."""
    r = read(results, name)
    if r is None or not r.get("probes"):
        return None
    probes = sorted(r["probes"].items(), key=lambda kv: float(kv[0]))
    order = (lambda kv: kv[0] != control) if control_first else (lambda kv: 0)
    cols = [(budget, arm, v, probe["arms"].get(control)) for budget, probe in probes
            for arm, v in sorted(probe["arms"].items(), key=order)]
    return r, probes, cols


def psnr_rows(r: dict, shipped: dict | None, cols: list, groups: dict) -> list[str]:
    """The table rows of an arms-against-a-control probe: each validation scene, then each group's mean (bold); a
    column for the shipped checkpoint, then one per ``(budget, arm, results, control results)`` of ``cols``."""
    lines = []
    for name in r["roles"]:
        row = [name] + ([cell(shipped["psnr"], None, shipped["psnr"].get(name), name)] if shipped else [])
        row += [cell(v["psnr"], c and c["psnr"], v["psnr"].get(name), name) for _, _, v, c in cols]
        lines.append("| " + " | ".join(row) + " |")
    for g, label in groups.items():
        row = [f"**{label}**"] + ([cell(shipped["means"], None, shipped["means"].get(g), g)] if shipped else [])
        row += [cell(v["means"], c and c["means"], v["means"].get(g), g) for _, _, v, c in cols]
        lines.append("| " + " | ".join(row) + " |")
    return lines


def section(results: Path) -> str | None:
    """Real objects on black or random backgrounds; None before a run."""
    got = probe_columns(results, "train_background.json", "white")
    if got is None:
        return None
    r, probes, cols = got
    s, shipped = r["settings"], r.get("shipped")
    head = (["scene"] + ([f"shipped gpnr-tiny (step {shipped['step']})"] if shipped else [])
            + [f"{arm}{' (control)' if arm == 'white' else ''}, {budget} CPU-s" for budget, arm, _, _ in cols])
    lines = ["### Real training objects on black or random backgrounds (`python -m bench train_background`)", "",
             "The lever the content test above points to, probed on validation data: `omnirecon train "
             "--real-background` composites the RGBA training objects (lego, chair) on `white` (as read, the "
             "control), `black`, or `random` (per step white, black or a uniform random flat colour, equal odds), "
             "the target and its sources on the same colour. Each arm continues checkpoints/gpnr-tiny (`--init`, "
             f"fresh optimizer, constant lr {s['lr']:g} after {s['warmup']} warm-up steps) for the same process-CPU "
             "budget (1 thread, seed 0; a longer probe continues the shorter one, which the constant schedule makes "
             f"the same run) on the shipped data mix (procedural rigs at weight 2 with {s['synth_scenes']} scenes "
             f"each, the real training scenes at 1), K drawn from [{s['num_views_range'][0]}, "
             f"{s['num_views_range'][1]}], a new scene every step (`--switch-every {s['switch_every']}`) so that lego "
             "and chair get their share of the few dozen steps; the arms draw the same scenes, views and pixels step "
             "for step, but reading lego and chair twice (on white and on black) costs the other arms a few steps. "
             f"Scored as `train_gpnr_gap` (the `cpu` protocol's targets and sources, 64 px, K = {s['num_views']}, mean "
             "PSNR over the targets, whole image, dB; in brackets the change against the control of the same budget), "
             "rendering as shipped (24 samples, bf16). Validation only: the held-out views of the real training "
             "scenes, lego and chair with a black background (the same objects the arms train on, on other views), "
             "the procedural validation seeds; fern, dtu_scan24/37 and the evaluation seeds are not looked at.", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += psnr_rows(r, shipped, cols, GROUPS)
    row = ["steps (on lego or chair)"] + (["-"] if shipped else []) + [f"{v['steps']} ({v['rgba_steps']})"
                                                                      for _, _, v, _ in cols]
    lines.append("| " + " | ".join(row) + " |")
    lines += [""] + [f"{budget} CPU-s per arm: {probe['verdict']}." for budget, probe in probes]
    for budget, probe in [kv for kv in probes if kv[1].get("figure")][-1:]:  # the longest probe's picture
        if probe.get("figure"):
            lines += ["", f"![chair on black, {budget} CPU-s per arm]({probe['figure']})", "",
                      f"chair with a black background, K = {s['num_views']}, each of the protocol's targets (rows): "
                      + " | ".join(probe["figure_columns"]) + f" ({budget} CPU-s per arm)."]
    arm = next(iter(probes[-1][1]["arms"].values()))
    lines += ["", f"Scoring: about {arm['eval_cpu_s']:.0f} CPU-s per checkpoint. The command of an arm: `{r['command']}`. "
              "A longer probe, `python -m bench train_background --cpu-budget B`, continues every arm from its longest "
              "shorter run and adds a column per arm.", ""]
    lines += continued_lines(r)
    return "\n".join(lines + [prov(p["provenance"]) + f" ({b} CPU-s probe)" for b, p in probes]
                     + [prov(c["provenance"]) + f" (continued {b} CPU-s)" for b, c in r.get("continued", {}).items()]
                     + [""])


def continued_lines(r: dict) -> list[str]:
    """The control arm trained further from the checkpoint shipped at the time (``--continue-shipped``): its
    validation means beside that checkpoint's, and whether it ships."""
    out = []
    for budget, c in sorted(r.get("continued", {}).items(), key=lambda kv: float(kv[0])):
        before, after, d = c["shipped"]["means"], c["continued"]["means"], c["change"]
        groups = "; ".join(f"{label.lower()} {before[g]:.2f} -> {after[g]:.2f} ({d[g]:+.2f})"
                           for g, label in GROUPS.items() if g in d)
        out += [f"**The control trained further** (`python -m bench train_background --continue-shipped --cpu-budget "
                f"{budget}`): the checkpoint shipped at step {c['parent_step']} ({c['parent_cpu_s']:.0f} CPU-s) "
                f"trained {c['cpu_s']:.0f} CPU-s more ({c['steps']} steps) with the control's settings, scored on the "
                f"same validation rows beside it: {groups}. "
                + ("Better by more than the bar on every real validation row and the procedural seeds: a candidate "
                   "to ship (`python -m bench train_tiny --reship`)." if c["better"] else
                   f"Not better by {c['bar_db']:g} dB on both every real validation row and the procedural seeds: not "
                   "shipped."), ""]
    return out

