"""The aspect and pool levers' section of BENCHMARKS.md reads only its results JSON: a column per arm and budget, the
control first, each other arm's PSNR with its change against the control of the same budget in brackets."""

import json
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[2] / "bench" / "results" / "train_gpnr_levers.json"


def test_section_gives_each_arm_against_the_control_of_its_budget(tmp_path):
    from bench.report.train_gpnr_levers import section

    assert section(tmp_path) is None  # no results: no section
    r = json.loads(RESULTS.read_text())
    budget, probe = max(r["probes"].items(), key=lambda kv: float(kv[0]))
    arm = next(a for a in probe["arms"] if a != "control")
    probe["arms"][arm]["means"]["procedural 4:3"] = probe["arms"]["control"]["means"]["procedural 4:3"] + 1.25
    (tmp_path / "train_gpnr_levers.json").write_text(json.dumps(r))
    text = section(tmp_path)
    header = next(line for line in text.splitlines() if line.startswith("| scene"))
    cols = [c.strip() for c in header.strip("|").split("|")]
    assert cols.index(f"control, {budget} CPU-s") < cols.index(f"{arm}, {budget} CPU-s")  # the control first
    row = next(line for line in text.splitlines() if line.startswith("| **mean: procedural validation seeds at 4:3**"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    planted, control = cells[cols.index(f"{arm}, {budget} CPU-s")], cells[cols.index(f"control, {budget} CPU-s")]
    assert planted.endswith("(+1.25)") and "(" not in control, (planted, control)
    assert len(cells) == len(cols) and f"{budget} CPU-s per arm:" in text
