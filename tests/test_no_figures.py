"""No measured figure in the package's code, help texts or docstrings: they say what a thing does and in what units;
every measured number lives in BENCHMARKS.md, with provenance (issue 45, item 4)."""

import re

from conftest import ROOT

PACKAGE = ROOT / "omnirecon"
FIGURES = {
    "a PSNR figure (N dB)": re.compile(r"(?<![\w.{])[+-]?\d+(?:\.\d+)?\s?dB\b"),
    "a frame-rate figure (N FPS)": re.compile(r"(?<![\w.{])\d+(?:\.\d+)?\s?FPS\b"),
    "a round of work (session / stop / round / issue N)": re.compile(r"\b(?:session|stop|round|issue) \d+\b", re.I),
}
"""What a measured figure looks like in source text. Units alone ("PSNR in dB", ``f"{psnr:.2f} dB"``) pass."""


def figures(text: str) -> list[tuple[int, str]]:
    """``(line number, what)`` for every measured figure in ``text``."""
    return [(n, what) for n, line in enumerate(text.splitlines(), 1) for what, pattern in FIGURES.items()
            if pattern.search(line)]


def test_the_patterns_tell_figures_from_units():
    assert figures('"""Held-out PSNR 24.01 dB."""') == [(1, "a PSNR figure (N dB)")]
    assert figures("# +0.3 dB on fern") == [(1, "a PSNR figure (N dB)")]
    assert figures("mesh path at 87 FPS") == [(1, "a frame-rate figure (N FPS)")]
    assert figures("before session 16") == [(1, "a round of work (session / stop / round / issue N)")]
    assert figures('"""PSNR in dB; frames per second (FPS)."""') == []
    assert figures('print(f"{psnr:.2f} dB, {fps:.1f} FPS")') == []
    assert figures("--val-margin: at least this many dB") == []


def test_no_measured_figure_in_the_package():
    found = [f"{path.relative_to(ROOT)}:{n}: {what}" for path in sorted(PACKAGE.rglob("*.py"))
             if "node_modules" not in path.parts for n, what in figures(path.read_text())]
    assert not found, ("measured figures belong in BENCHMARKS.md (say what the code does, in what units, and name the "
                       "BENCHMARKS section):\n" + "\n".join(found))
