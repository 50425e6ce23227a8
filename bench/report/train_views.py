"""BENCHMARKS.md section: source-view count and baseline on validation (`python -m bench train_views`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import missing, prov, read, stale_note


def section(results: Path) -> str:
    """omnirecon-tiny's K = 10 against its trained K = 4 (``render_views``), and every model under DTU-like wide
    baselines, on validation data only."""
    r = read(results, "train_views.json")
    if r is None:
        return missing("train_views.json")
    out = ["## Source views on validation: count and baseline (`python -m bench train_views`)", "",
           "Validation data only (procedural seeds 901000, 901002, 901004 and the held-out views of lego, chair, fox, "
           "ethiopianHead; `cpu` protocol, 64 px, PSNR in dB, whole image).", ""]
    c = r.get("count")
    if c:
        out += stale_note("omnirecon-tiny", c["checkpoint"], "train_views")
        out += ["**omnirecon-tiny by source count.** It was trained at K = 4 only. `K10_render_views4`: 10 sources "
                "given, rendered from the 4 nearest the target (the shipped `render_views: 4`).", "",
                "| setting | procedural | real (held-out views) |", "|---|---|---|"]
        out += [f"| {name} | {m.get('procedural', float('nan')):.2f} | {m.get('real', float('nan')):.2f} |"
                for name, m in c["means"].items()]
        out += ["", f"{c['cpu_s']:.0f} CPU-s. Held-out views at K = 10 (GT | render | error; rows: ethiopianHead all "
                "10 sources, the nearest 4; lego all 10, the nearest 4): with all 10 the colour blend ghosts.", "",
                "![omnirecon-tiny K = 10](bench/results/figures/train_views_omnirecon_k10.png)", ""]
    w = r.get("wide")
    if w:
        names = [s[0] for s in w["settings"]]
        out += ["**Wide baselines** (object-rig validation scenes " + ", ".join(w["scenes"]) + "): `K3_min25deg` "
                "gives each target the 3 nearest pool views at least 25 degrees away, `K10_min10deg` the 10 nearest "
                "at least 10 degrees away, as DTU's protocol does (its nearest source is 29 degrees from the targets "
                "on average at K = 3, 12 at K = 10; 3-5 degrees on lego and ethiopianHead). `min0deg`: the "
                "protocol's nearest views. Mean PSNR over the scenes:", "",
                "| model | " + " | ".join(names) + " | CPU-s |", "|---|" + "---|" * (len(names) + 1)]
        notes = [line for model, m in w["models"].items() for line in stale_note(model, m["checkpoint"], "train_views")]
        out[-2:-2] = notes  # before the table
        for model, m in w["models"].items():
            out.append(f"| {model} | " + " | ".join(f"{m['mean'][n]:.2f}" for n in names) + f" | {m['cpu_s']:.0f} |")
        out.append("")
    out.append(prov(r["provenance"]))
    return "\n".join(out)
