"""The package's layers (docs/architecture.md) as checks that fail when the code drifts from them."""

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "omnirecon"
BENCH = ROOT / "bench"
MAX_LINES = 400
"""Modules over this many lines say why at their top, in a line starting ``Size:``."""


def contracts() -> list[dict]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]


def test_import_contract_is_kept():
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which("lint-imports")
    assert exe, "import-linter is part of the test extra (pip install -e '.[test]')"
    proc = subprocess.run([exe, "--config", str(ROOT / "pyproject.toml")], capture_output=True, text=True, cwd=ROOT,
                          timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "0 broken" in proc.stdout


def test_layers_cover_every_package_folder_and_top_module():
    layers = next(c for c in contracts() if c["type"] == "layers")["layers"]
    named = {m.strip() for layer in layers for m in layer.split("|")}
    folders = {f"omnirecon.{p.parent.name}" for p in PACKAGE.glob("*/__init__.py")}
    modules = {f"omnirecon.{p.stem}" for p in PACKAGE.glob("*.py") if p.stem != "__init__"}
    assert folders - named == set(), "every package folder must sit in a layer"
    assert modules - named == set(), "every top-level module must sit in a layer"


def test_commands_are_thin_and_independent():
    independence = next(c for c in contracts() if c["type"] == "independence")
    assert independence["modules"] == ["omnirecon.commands.*"]
    for path in (PACKAGE / "commands").glob("*.py"):
        tree = ast.parse(path.read_text())
        imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        assert not any(m.startswith("omnirecon.commands") for m in imported), path
        assert len(path.read_text().splitlines()) <= 100, f"{path} is a command: keep the work in the library"


def test_long_modules_say_why():
    long = []
    for path in [*PACKAGE.rglob("*.py"), *BENCH.rglob("*.py")]:
        if "node_modules" in path.parts:
            continue
        lines = path.read_text().splitlines()
        if len(lines) > MAX_LINES:
            doc = ast.get_docstring(ast.parse("\n".join(lines))) or ""
            if not any(line.startswith("Size:") for line in doc.splitlines()):
                long.append(f"{path.relative_to(ROOT)} ({len(lines)} lines)")
    assert not long, f"modules over {MAX_LINES} lines need a 'Size:' line in their docstring: {long}"


MAX_WORKFLOW_FUNCTION = 45
"""Lines (``def`` to its last line, nested functions included) a function of ``omnirecon/workflows/`` may have:
a workflow reads as named steps (checks, computation, pictures, writing), each short enough to see at a glance."""


def test_workflow_functions_are_short():
    long = []
    for path in sorted((PACKAGE / "workflows").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_WORKFLOW_FUNCTION:
                    long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, f"workflow functions over {MAX_WORKFLOW_FUNCTION} lines: split them into named steps: {long}"


def test_cli_registry_points_at_commands():
    from omnirecon.cli import COMMANDS

    for name, spec in COMMANDS.items():
        module = spec.split(":")[0]
        assert module == f"omnirecon.commands.{name}", (name, spec)
        assert (PACKAGE / "commands" / f"{name}.py").is_file()


def _bench_imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    names |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {f"{n.module}.{a.name}" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module == "bench"
              for a in n.names}
    return {m for m in names if m == "bench" or m.startswith("bench.")}


def test_bench_measures_apart_from_its_markdown():
    """bench/<name>.py measure and write JSON; bench/report/ writes Markdown from that JSON only; only the page
    (and the entry point) use both. The layers contract keeps omnirecon from importing bench."""
    for path in (BENCH / "report").glob("*.py"):
        assert {m for m in _bench_imports(path) if not m.startswith("bench.report")} == set(), path
    for path in BENCH.glob("*.py"):
        if path.stem not in ("page", "__main__"):
            assert not any(m.startswith("bench.report") for m in _bench_imports(path)), path
    layers = next(c for c in contracts() if c["type"] == "layers")["layers"]
    assert layers[0] == "bench"
