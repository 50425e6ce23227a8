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


def test_continued_run_says_whether_it_ships(tmp_path):
    """A run continued from the shipped checkpoint (``--continue-shipped``) is one paragraph: each validation mean
    before -> after with its change, and "not shipped" unless it clears the bar on both groups."""
    from bench.report.train_background import section

    r = json.loads(RESULTS.read_text())
    means = {"real": 25.0, "black": 24.0, "validation": 24.7, "procedural": 27.0}
    after = {**means, "real": 25.5, "validation": 25.2}  # better on the real rows only
    c = {"parent_step": 9695, "parent_cpu_s": 14632.0, "steps": 1111, "cpu_s": 2400.0, "bar_db": 0.1,
         "shipped": {"means": means}, "continued": {"means": after},
         "change": {g: round(after[g] - means[g], 3) for g in means}, "better": False,
         "provenance": r["provenance"]}
    r["continued"] = {"2400": c}
    (tmp_path / "train_background.json").write_text(json.dumps(r))
    text = section(tmp_path)
    line = next(x for x in text.splitlines() if x.startswith("**The control trained further**"))
    assert "every real validation row 24.70 -> 25.20 (+0.50)" in line and "not shipped" in line
    c["better"] = True
    (tmp_path / "train_background.json").write_text(json.dumps(r))
    assert "a candidate to ship" in section(tmp_path)
