"""``omnirecon`` command line: one tyro subcommand per task.

Each subcommand is a dataclass config with a ``main()`` method in :mod:`omnirecon.commands`, registered
in ``COMMANDS`` as ``"name": "module:ClassName"`` and imported only when chosen. Bad input exits with code 2 and a
one-line message; ``--verbose`` (anywhere on the line) shows the traceback.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import re
import sys
import traceback
import warnings

from omnirecon.errors import EXIT_BAD_INPUT, InputError

COMMANDS: dict[str, str] = {
    "demo": "omnirecon.commands.demo:DemoCommand",
    "synth": "omnirecon.commands.synth:SynthCommand",
    "process": "omnirecon.commands.process:ProcessCommand",
    "inspect": "omnirecon.commands.inspect:InspectCommand",
    "eval": "omnirecon.commands.eval:EvalCommand",
    "render": "omnirecon.commands.render:RenderCommand",
    "train": "omnirecon.commands.train:TrainCommand",
    "mesh": "omnirecon.commands.mesh:MeshCommand",
    "lift": "omnirecon.commands.lift:LiftCommand",
    "edit": "omnirecon.commands.edit:EditCommand",
    "pet": "omnirecon.commands.pet:PETCommand",
    "finetune": "omnirecon.commands.finetune:FinetuneCommand",
    "export": "omnirecon.commands.export:ExportCommand",
    "view": "omnirecon.commands.view:ViewCommand",
    "bench": "omnirecon.commands.bench:BenchCommand",
    "reconstruct": "omnirecon.commands.reconstruct:ReconstructCommand",
    "doctor": "omnirecon.commands.doctor:DoctorCommand",
}
"""Each verb's ``"module:ClassName"``; its help is the class's docstring (``omnirecon VERB --help``)."""


def _load(spec: str):
    module, name = spec.split(":")
    return getattr(importlib.import_module(module), name)


_ROLE = re.compile(r":(?:data|mod|func|class|meth|attr|obj|exc|ref):`(~?)([^`<]*?)(?:\s*<([^>]*)>)?`")
"""A Sphinx cross-reference in a docstring: ``:func:`name```, ``:func:`~a.b.name``` (shown as ``name``) or
``:ref:`text <target>```."""


def _plain(text: str) -> str:
    """Sphinx roles and inline-literal backticks of a docstring as plain text for a terminal: ``:data:`a.B```
    -> ``a.B``, ``:func:`~a.b.f``` -> ``f``, a double-backquoted literal -> the literal."""
    def role(m: re.Match) -> str:
        name = m.group(2).strip()
        return name.rsplit(".", 1)[-1] if m.group(1) else name

    return _ROLE.sub(role, text).replace("``", "")


def reflow_help(text: str) -> str:
    """A docstring as help text: its lines dedented (``inspect.cleandoc``) and joined into paragraphs; blank lines
    part paragraphs and a line opening a list item (``- ``, ``* ``) starts a new line; Sphinx roles and literal
    backquotes read as plain text (:func:`_plain`)."""
    import inspect

    text = _plain(text)
    paragraphs = []
    for para in inspect.cleandoc(text).split("\n\n"):
        lines: list[str] = []
        for line in para.splitlines():
            line = line.strip()
            if lines and not line.startswith(("- ", "* ")):
                lines[-1] += f" {line}"
            elif line:
                lines.append(line)
        paragraphs.append("\n".join(lines))
    return "\n\n".join(p for p in paragraphs if p)


def _use_reflow() -> None:
    """tyro joins a docstring's lines before removing their indentation, so an indented continuation line starts a
    new line of the help; its joiner is replaced by :func:`reflow_help` (where this tyro has it)."""
    import tyro._strings as tyro_strings

    if hasattr(tyro_strings, "remove_single_line_breaks"):
        tyro_strings.remove_single_line_breaks = reflow_help


def main(argv: list[str] | None = None) -> int:
    import tyro

    _use_reflow()

    argv = list(sys.argv[1:] if argv is None else argv)
    verbose = any(a in ("--verbose", "-v") for a in argv)
    argv = [a for a in argv if a not in ("--verbose", "-v")]
    try:
        # Import only the chosen subcommand (fast start, no heavy optional imports).
        chosen = next((a for a in argv if not a.startswith("-")), None)
        names = [chosen] if chosen in COMMANDS else list(COMMANDS)
        configs = {n: _load(COMMANDS[n]) for n in names}
        box = io.StringIO()  # tyro's multi-line error box, turned into one line below
        try:
            with contextlib.redirect_stderr(box):
                config = tyro.extras.subcommand_cli_from_dict(
                    configs, args=argv, prog="omnirecon",
                    description="Generalizable image-based reconstruction and rendering. "
                    "Add --verbose anywhere for full tracebacks.",
                )
        except SystemExit as e:
            if e.code in (0, None):
                sys.stderr.write(box.getvalue())
                raise
            from omnirecon.cli_errors import parse_error_line

            print(f"omnirecon: error: {parse_error_line(box.getvalue(), chosen if chosen in COMMANDS else None)}",
                  file=sys.stderr)
            return EXIT_BAD_INPUT
        from omnirecon.options import check_options

        check_options(chosen, config)  # every numeric option of every verb, before any work
        sys.stderr.write(box.getvalue())  # notes printed while the options were parsed (e.g. a large --chunk)
        with warnings.catch_warnings(record=True) as caught:  # libraries' warnings: kept off stderr ...
            warnings.simplefilter("default")
            try:
                config.main()
            except BaseException:
                _notes(caught, verbose, failed=True)
                raise
            _notes(caught, verbose, failed=False)
    except InputError as e:
        print(f"omnirecon: error: {e.one_line()}", file=sys.stderr)
        if verbose:
            traceback.print_exc()  # the traceback, and still the bad-input exit code
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("omnirecon: interrupted", file=sys.stderr)
        return 130
    return 0


def _notes(caught: list, verbose: bool, failed: bool) -> None:
    """... and shown after a run that succeeded as one line each (unique, at most 3), or in full with
    ``--verbose``; after an error only its one line is printed."""
    if verbose:
        for w in caught:
            print(warnings.formatwarning(w.message, w.category, w.filename, w.lineno).rstrip(), file=sys.stderr)
        return
    if failed:
        return
    seen = list(dict.fromkeys(f"{w.category.__name__}: {' '.join(str(w.message).split())[:200]}" for w in caught))
    for text in seen[:3]:
        print(f"omnirecon: note: {text}", file=sys.stderr)


def entry() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entry()
