"""What the section renderers share: reading a results file, the provenance line, the stale-checkpoint note."""

from __future__ import annotations

import json
from pathlib import Path

from omnirecon.engine.checkpoint import VIEW_CAP, VOLUMETRIC_ONLY, ignoring  # noqa: F401 - the sections and tests take them from here

ROOT = Path(__file__).resolve().parents[2]
QUALITY_MODELS = ("floor", "gpnr-tiny", "ibrnet-tiny", "omnirecon-tiny")
GEOMETRY_MODELS = ("floor", "ibrnet-tiny", "omnirecon-tiny")


def read(results: Path, name: str) -> dict | None:
    """``results/name`` parsed, or None when that benchmark has not run."""
    f = results / name
    return json.loads(f.read_text()) if f.is_file() else None


def missing(name: str) -> str:
    return f"*{name}: not measured yet (run `python -m bench page`).*"


def prov(p: dict) -> str:
    from omnirecon.provenance import markdown_header

    text = markdown_header(p)
    return text + (f" — {p['note']}" if p.get("note") else "")


def table_section(results: Path, name: str, title: str, intro: str, columns: list[str], line) -> str | None:
    """A section that is one table over ``results/name``'s rows: ``title``, ``intro``, a header of ``columns``, one
    line per row by ``line(row)`` (the cells between the bars), then the provenance; None when no rows were measured."""
    r = read(results, name)
    if not r or not r.get("rows"):
        return None
    out = [f"## {title}", "", intro, "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    out += [f"| {line(row)} |" for row in r["rows"]]
    return "\n".join([*out, "", prov(r["provenance"]), ""])


def num(v, digits: int = 4) -> str:
    return "–" if v is None or v != v else f"{v:.{digits}f}"


def scene_rows(r: dict) -> dict[str, dict[str, dict]]:
    """``{row name: {K: mean metrics}}``: the procedural set averaged, real scenes one row each."""
    rows: dict[str, dict[str, dict]] = {}
    synth = [s for s in r["scenes"] if s["protocol"] == "synth"]
    if synth:
        rows[f"synth:eval ({len(synth)} scenes)"] = {k: v for k, v in r["means"].get("synth", {}).items()}
    for s in r["scenes"]:
        if s["protocol"] != "synth":
            rows[s["name"]] = {k: v["mean"] for k, v in s["settings"].items()}
    return rows


_SHIPPED: dict = {}

def shipped_fingerprint(model: str, ignore: tuple[str, ...] = (), long_side: int | None = None) -> dict | None:
    """The fingerprint of ``checkpoints/<model>`` as it ships now, without the config keys ``ignore`` (None when
    absent); ``long_side``: of the weights it loads for a render of that size (px; its ``sizes/``)."""
    from omnirecon.engine.checkpoint import fingerprint, folder_for_size

    key = (model, tuple(ignore), long_side)
    if key not in _SHIPPED:
        folder = ROOT / "checkpoints" / model
        if (folder / "model.safetensors").is_file():
            folder = folder_for_size(folder, long_side)
        _SHIPPED[key] = fingerprint(folder, ignore) if (folder / "model.safetensors").is_file() else None
    return _SHIPPED[key]


def stale_note(model: str, recorded: dict | None, script: str, ignore: tuple[str, ...] = (),
               long_side: int | None = None) -> list[str]:
    """A warning line when stored results were not measured with the checkpoint that ships now.

    ``ignore``: config keys the section's numbers do not depend on (e.g. :data:`VOLUMETRIC_ONLY` for the
    mesh path). Then the results are current when their ``sha256_ignoring`` (recorded with the same keys
    left out) equals the shipped checkpoint's fingerprint without those keys, or, for results recorded
    before the keys existed, when their full ``sha256`` does (the config then had none of them). Results recorded
    without fewer keys (their ``ignored_keys`` a subset of ``ignore``) are current when their ``sha256_ignoring``
    equals the shipped fingerprint without ``ignore`` (the other keys did not exist then) or without their own."""
    now = shipped_fingerprint(model, long_side=long_side)
    recorded = recorded or {}
    if now is None or (recorded.get("sha256") and recorded["sha256"] == now["sha256"]):
        return []
    if ignore:
        part = shipped_fingerprint(model, ignore, long_side)["sha256"]
        keys = tuple(sorted(recorded.get("ignored_keys") or []))  # recorded without these; the section reads none
        fits = bool(keys) and set(keys) <= set(ignore) and recorded.get("sha256_ignoring") in (
            part, shipped_fingerprint(model, keys, long_side)["sha256"])  # ignore's other keys: absent then, or unchanged
        if recorded.get("sha256") == part or fits:
            return []
    used = (f"step {recorded['step']}" if recorded.get("step") is not None else "an unrecorded checkpoint") + (
        f", fingerprint {recorded['sha256']}" if recorded.get("sha256") else "")
    where = Path(now["path"]).relative_to(ROOT) if Path(now["path"]).is_relative_to(ROOT) else now["path"]
    return [f"> **Stale:** the {model} numbers here were measured with {used}; `{where}` is now step "
            f"{now['step']} (fingerprint {now['sha256']}"
            + (f"; {part} without the config keys {', '.join(ignore)} these numbers do not depend on" if ignore else "")
            + f"). Rerun `python -m bench {script}`.", ""]
