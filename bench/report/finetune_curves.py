"""BENCHMARKS.md section: Fine-tuning curves of the mesh path (`python -m bench finetune_curves`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import missing, prov, read


def section(results: Path) -> str:
    """The mesh path's held-out PSNR against seconds of CPU tuning, with coverage (python -m bench finetune_curves)."""
    r = read(results, "finetune_curves.json")
    if r is None:
        return missing("finetune_curves.json")
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
        "## Fine-tuning curves of the mesh path (`python -m bench finetune_curves`)",
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
        prov(r["provenance"]),
    ])
