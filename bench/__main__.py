"""The one entry point: ``python -m bench <name> [args]`` runs ``bench/<name>.py``'s ``main(args)``."""

from __future__ import annotations

import ast
import importlib
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def names() -> dict[str, str]:
    """``{name: first line of its docstring}`` for every module of bench/ with a ``main``, and every package whose
    ``__init__.py`` defines or imports one (read, not imported)."""
    out = {}
    files = {f.stem: f for f in HERE.glob("*.py")} | {f.parent.name: f for f in HERE.glob("*/__init__.py")}
    for name, f in sorted(files.items()):
        tree = ast.parse(f.read_text())
        if not name.startswith("_") and any(
                (isinstance(n, ast.FunctionDef) and n.name == "main")
                or (isinstance(n, ast.ImportFrom) and any(a.name == "main" for a in n.names)) for n in tree.body):
            out[name] = (ast.get_docstring(tree) or "").splitlines()[0]
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    known = names()
    if not argv or argv[0] in ("-h", "--help"):
        import bench

        print(bench.__doc__.split("\n\n")[1].rstrip() + "\n\nbenchmarks (bench/<name>.py):")
        print("\n".join(f"  {n:16s} {doc}" for n, doc in known.items()))
        return 0
    if argv[0] not in known:
        print(f"error: no benchmark named {argv[0]!r}; `python -m bench --help` lists them", file=sys.stderr)
        return 2
    sys.argv = [f"python -m bench {argv[0]}", *argv[1:]]  # so each module's --help names the right command
    importlib.import_module(f"bench.{argv[0]}").main(argv[1:])
    return 0


if __name__ == "__main__":
    sys.exit(main())
