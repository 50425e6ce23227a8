"""What the section renderers share: reading a results file, the provenance line, the stale-checkpoint note."""

from __future__ import annotations

import json
from pathlib import Path

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


def shipped_fingerprint(model: str) -> dict | None:
    """The fingerprint of ``checkpoints/<model>`` as it ships now (None when absent)."""
    from omnirecon.engine.checkpoint import fingerprint

    if model not in _SHIPPED:
        folder = ROOT / "checkpoints" / model
        _SHIPPED[model] = fingerprint(folder) if (folder / "model.safetensors").is_file() else None
    return _SHIPPED[model]


def stale_note(model: str, recorded: dict | None, script: str) -> list[str]:
    """A warning line when stored results were not measured with the checkpoint that ships now."""
    now = shipped_fingerprint(model)
    recorded = recorded or {}
    if now is None or (recorded.get("sha256") and recorded["sha256"] == now["sha256"]):
        return []
    used = (f"step {recorded['step']}" if recorded.get("step") is not None else "an unrecorded checkpoint") + (
        f", fingerprint {recorded['sha256']}" if recorded.get("sha256") else "")
    return [f"> **Stale:** the {model} numbers here were measured with {used}; `checkpoints/{model}` is now step "
            f"{now['step']} (fingerprint {now['sha256']}). Rerun `python -m bench {script}`.", ""]
