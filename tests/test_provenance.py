"""The provenance commit: ``+dirty`` for changed code, not for changed benchmark results."""

import subprocess

from omnirecon.provenance import git_commit


def _git(root, *args):
    subprocess.run(["git", *args], cwd=root, check=True, capture_output=True)


def test_results_files_do_not_make_the_commit_dirty(tmp_path):
    _git(tmp_path, "init", "-q")
    (tmp_path / "bench" / "results").mkdir(parents=True)
    for name in ("code.py", "BENCHMARKS.md", "bench/results/rows.json"):
        (tmp_path / name).write_text("a\n")
    _git(tmp_path, "add", ".")
    _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "x")
    clean = git_commit(tmp_path)
    assert len(clean) == 12 and not clean.endswith("+dirty")
    (tmp_path / "bench" / "results" / "rows.json").write_text("b\n")
    (tmp_path / "BENCHMARKS.md").write_text("b\n")
    assert git_commit(tmp_path) == clean  # a bench run writing its rows
    (tmp_path / "code.py").write_text("b\n")
    assert git_commit(tmp_path) == clean + "+dirty"
