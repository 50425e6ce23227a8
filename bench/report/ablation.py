"""BENCHMARKS.md section: GPNR ablations at the tiny budget (`python -m bench ablation_gpnr`)."""

from __future__ import annotations

from pathlib import Path

from bench.report.common import missing, prov, read


def section(results: Path) -> str:
    r = read(results, "ablation_gpnr.json")
    if r is None:
        return missing("ablation_gpnr.json")
    out = ["## GPNR ablations at the tiny budget (`python -m bench ablation_gpnr`)", "",
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
    return "\n".join([*out, "", prov(r["provenance"])])
