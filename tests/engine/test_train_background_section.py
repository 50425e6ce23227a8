"""The background-lever section of BENCHMARKS.md reads only its results JSON: a column per arm and budget, each arm's
PSNR with its change against the white control of the same budget in brackets."""

import json
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[2] / "bench" / "results" / "train_background.json"


def test_section_gives_each_arm_against_the_control_of_its_budget(tmp_path):
    from bench.report.train_background import section

    assert section(tmp_path) is None  # no results: no section
    r = json.loads(RESULTS.read_text())
    budget, probe = max(r["probes"].items(), key=lambda kv: float(kv[0]))
    arm = next(a for a in probe["arms"] if a != "white")  # the longest probe's first arm beside the control
    probe["arms"][arm]["means"]["black"] = probe["arms"]["white"]["means"]["black"] + 1.25  # a planted change
    (tmp_path / "train_background.json").write_text(json.dumps(r))
    text = section(tmp_path)
    header = next(line for line in text.splitlines() if line.startswith("| scene"))
    cols = [c.strip() for c in header.strip("|").split("|")]
    row = next(line for line in text.splitlines() if line.startswith("| **mean: lego and chair on black**"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    planted = cells[cols.index(f"{arm}, {budget} CPU-s")]
    control = cells[cols.index(f"white (control), {budget} CPU-s")]
    assert planted.endswith("(+1.25)") and "(" not in control, (planted, control)
    assert len(cells) == len(cols) and f"{budget} CPU-s per arm:" in text
