"""BENCHMARKS.md section: a shipped checkpoint trained further at 256 px, chosen on validation (`python -m bench
train_256`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import prov, read

MODEL_FILES = ("train_256.json", "train_256_omnirecon-tiny.json", "train_256_gpnr-tiny.json")
"""One results file per model (`python -m bench train_256 --model M`; ibrnet-tiny's has the plain name)."""


def section(results: Path) -> str | None:
    parts = [text for name in MODEL_FILES if (text := _model_section(results, name))]
    return "\n".join(parts) if parts else None


def _model_section(results: Path, name: str) -> str | None:
    r = read(results, name)
    if not r or len(r.get("rows", [])) < 2:
        return None
    shipped, run = r["rows"][:2]
    mixed = [m for f in sorted(results.glob("train_256_mix*.json")) if (m := read(results, f.name))
             and len(m.get("rows", [])) >= 2 and m.get("model") == r["model"]]
    scenes = sorted(shipped["256"]["scenes"], key=lambda n: (not n.startswith("synth:"), n))
    head = ["checkpoint", "steps", "training CPU-s", *(f"{n} 256 px" for n in scenes), "procedural 256 px", "real 256 px",
            "procedural 64 px", "real 64 px"]

    def line(row: dict) -> str:
        cells = [row["name"], f"{row['step']:,}", f"+{row['cpu_s']:,.0f}" if row.get("cpu_s") else "–",
                 *(f"{row['256']['scenes'].get(n, float('nan')):.2f}" for n in scenes),
                 *(f"**{row[s][g]:.2f}**" if s in row else "–" for s in ("256", "64") for g in ("procedural", "real"))]
        return "| " + " | ".join(cells) + " |"

    def gains(row: dict) -> str:
        return ", ".join(f"{g} {s} px {row[s][g] - shipped[s][g]:+.2f}" for s in ("256", "64")
                         for g in ("procedural", "real"))

    full = r["rows"][2:]  # --full-render: the same states at 256 px with the trained sample counts
    runs = [run, *full, *(m["rows"][1] for m in mixed)]
    cost = [f"{row['name']} " + " / ".join(f"{row[s]['cpu_s']:.0f}" for s in ("256", "64")) + " CPU-s"
            for row in (shipped, *runs) if all(row.get(s, {}).get("cpu_s") for s in ("256", "64"))]
    mix_text = []
    for m in mixed:
        row = m["rows"][1]
        mix_text += [f"**Half the scenes at {m['mix']} px** (`python -m bench train_256 --mix {m['mix']}`: the same warm "
                     f"start with `--mix-resolution {m['mix']} --mix-share 0.5`, every scene drawn read at {m['mix']} px "
                     f"with odds 1/2, so that the run keeps the size the checkpoint was chosen at): run minus shipped: "
                     f"{gains(row)}. Decision: {m['decision']}"
                     + ("" if isinstance(m.get("ships"), str) or m.get("ships") is None else
                        ", when a run could only replace the weights") + ".", "", f"Command of the run: `{m['command']}`.", "",
                     prov(m["provenance"]), ""]
    return "\n".join([
        f"### {r['model']} trained further at {r['size']} px (`python -m bench train_256`, issue 47)", "",
        f"The shipped {r['model']} (trained at 64 px) continued at {r['size']} px: a warm start (`--init`, fresh "
        "optimizer, peak lr 1e-4 after 20 warm-up steps, cosine), the shipped data mix read at 256 px (procedural rigs "
        f"generated at 256 px), {_views(r['command'])}, seed 0, 1 thread, niced beside other work. Scored on validation "
        "only, K = 3, whole-image PSNR (dB): `omnirecon eval --protocol-set cpu256` (full sampling) and `--protocol-set "
        "cpu` (64 px) on the procedural validation seeds (one per rig, generated at each size) and the held-out views "
        "of the real training scenes; fern, dtu_scan24/37 and the evaluation seeds are not looked at. The rule: a run "
        f"that beats the shipped weights by more than {r['margin_db']:g} dB on both groups at 256 px and loses at most "
        f"{r['margin_db']:g} dB on either at 64 px replaces them; one that beats them at 256 px but loses at 64 px "
        "ships as the checkpoint's 256-px weights (`checkpoints/<model>/sizes/256/`: `eval`, `render` and the demo "
        "load the weights trained nearest the size they render at, so the 64-px rows keep the own weights); with "
        "`--full-render` (rows `full render`) or `--samples N` (rows `N samples`), a state rendered with its trained "
        "sample counts or with N samples per ray that beats the shipped "
        "checkpoint, and a winning run, by more than that on both groups at 256 px ships as the 256-px weights with "
        "those render options"
        + ("" if isinstance(r.get("ships"), str) or r.get("ships") is None else
           " (this run was decided when a run could only replace the weights)") + ".", "",
        "| " + " | ".join(head) + " |", "|" + "---|" * len(head), line(shipped), *map(line, runs), "",
        f"Run minus shipped ({run['name']}): {gains(run)}."
        + "".join(f" {row['name']} minus shipped at 256 px: " + ", ".join(
            f"{g} {row['256'][g] - shipped['256'][g]:+.2f}" for g in ("procedural", "real")) + "." for row in full)
        + (" Rows `full render`: every render option at its full-render value (the trained sample counts; the "
           "other rows render with the checkpoint's own options, e.g. ibrnet-tiny's 16 + 16 samples), at 256 px only."
           if any(row.get("render") == "full" for row in full) else "")
        + (" Rows `N samples`: N samples per ray, the other render options as shipped, at 256 px only "
           "(`--samples N`)." if any(row.get("render") == "samples" for row in full) else "")
        + f" Decision: {r['decision']}."
        + (" Not carried out: the bench ran without `--ship` (the checkpoint is unchanged; the run's README in "
           "`checkpoints/runs/` says why)." if r.get("ships") and not r.get("shipped") else "")
        + (f" Scoring cost at 256 / 64 px (1 thread, beside other work): {'; '.join(cost)}." if cost else ""),
        "", f"Command of the run: `{r['command']}`.", "", prov(r["provenance"]), "", *mix_text])


def _views(command: str) -> str:
    """How the run's command draws the source-view count K."""
    words = command.split()
    if "--num-views-range" in words:
        i = words.index("--num-views-range")
        return f"K drawn from [{words[i + 1]}, {words[i + 2]}]"
    return "K fixed at the preset's count, as the checkpoint was trained"
