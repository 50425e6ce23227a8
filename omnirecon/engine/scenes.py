"""Scene preparation shared by every command: read a scene at its protocol's resolution, normalised,
and generate (or reuse) the held-out procedural set ``synth:eval``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from omnirecon.data import ReadOptions, detect_format, load_scene
from omnirecon.data.scene import Scene
from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.engine.held import held
from omnirecon.engine.protocols import (
    FORMAT_PROTOCOL,
    PROTOCOL_SETS,
    PROTOCOLS,
    SYNTH_PREFIX,
    SYNTH_VIEWS,
    Protocol,
    protocol_for,
)
from omnirecon.errors import InputError
from omnirecon.options import check_value
from omnirecon.scene_kind import scene_kind
from omnirecon.splits import EVAL_SEEDS


def _read(path: Path, fmt: str, options: ReadOptions) -> Scene:
    """``load_scene``, read once while a run holds its reads (:mod:`omnirecon.engine.held`)."""
    kind = "scene_probe" if options.max_views == 1 else "scene"
    return held(kind, (str(Path(path).resolve()), fmt, repr(options)), lambda: load_scene(path, fmt, options))


def load_at_resolution(path: Path, long_side: int, background: str = "white", fmt: str = "auto") -> Scene:
    """Read ``path`` with its long side area-downscaled to at most ``long_side`` px, normalised
    (``Scene.normalized``: content centred in the unit sphere, as training does)."""
    check_value("resolution", long_side)  # the rule: omnirecon/options.py
    fmt = detect_format(path) if fmt == "auto" else fmt
    probe = _read(path, fmt, ReadOptions(max_views=1))  # one image: the native size
    native = max(probe.width, probe.height)
    scene = _read(path, fmt, ReadOptions(downscale=max(1.0, native / long_side), background=background))
    return scene.normalized()


def photo_side(path: Path, cap: int = 512, fmt: str = "auto") -> int:
    """The long side of the scene's photos in pixels, at most ``cap`` (what users look at)."""
    fmt = detect_format(path) if fmt == "auto" else fmt
    probe = _read(path, fmt, ReadOptions(max_views=1))
    return min(cap, max(probe.width, probe.height))


def object_masks(path: Path, fmt: str = "auto") -> bool:
    """The scene is an object capture (``rig == "object"``) with object masks, e.g. photos processed with
    ``--masks``, DTU, ethiopianHead: what ``reconstruct`` meshes with its masks."""
    fmt = detect_format(path) if fmt == "auto" else fmt
    probe = _read(path, fmt, ReadOptions(max_views=1))
    kind = scene_kind(probe)
    return kind.object and kind.masks


@dataclass
class EvalScene:
    """A scene ready for evaluation."""

    name: str
    """Unique name in the results (the folder name)."""
    scene: Scene
    """The scene at protocol resolution, normalised."""
    protocol: Protocol
    """Its protocol."""
    path: Path | None = None
    """Where it was read from."""


def synth_eval_paths(spec: str, count: int = 10, cache: Path = Path("outputs/cache"), progress=None) -> list[Path]:
    """Generate (or reuse) the held-out procedural scenes of ``spec`` (``synth:eval[:rig]``).

    Scene ``i`` uses seed ``EVAL_SEEDS[i]`` and is written to ``cache/synth_eval/<rig>_<res>``.
    A cached scene written with other options or by another generator version is regenerated.
    """

    parts = spec.split(":")
    rig = parts[2] if len(parts) > 2 else "object"
    if parts[:2] != ["synth", "eval"] or len(parts) > 3 or rig not in ("object", "frontal", "forward"):
        raise InputError(f"bad scene spec {spec!r}", None, "use synth:eval, synth:eval:object, synth:eval:frontal "
                         "or synth:eval:forward")
    check_value("synth_count", count)  # the rule: omnirecon/options.py
    res = PROTOCOLS["synth"].long_side
    out = Path(cache) / "synth_eval" / f"{rig}_{res}"
    options = SynthOptions(rig=rig, views=SYNTH_VIEWS, resolution=res)
    task = progress.add_task(f"synth {rig}", total=count) if progress is not None else None
    paths = []
    for seed in EVAL_SEEDS[:count]:
        paths.append(generate_scene(out, seed, options))  # regenerated when its options or version differ
        if task is not None:
            progress.advance(task)
    return paths


def prepare_scenes(specs, count: int = 10, cache: Path = Path("outputs/cache"), progress=None,
                   protocol_set: str = "full") -> list[EvalScene]:
    """Load every scene of ``specs`` (paths, ``synth:eval[:rig]`` or :class:`Scene` objects) under the
    protocols of ``protocol_set``."""
    if protocol_set not in PROTOCOL_SETS:
        raise InputError(f"unknown protocol set {protocol_set!r}", None, f"use one of {', '.join(PROTOCOL_SETS)}")
    paths: list = []
    for spec in specs:
        if isinstance(spec, Scene):
            paths.append(spec)
        elif str(spec).startswith(SYNTH_PREFIX):
            paths.extend(synth_eval_paths(str(spec), count, cache, progress))
        else:
            detect_format(Path(spec))  # fail fast, before any scene is read
            paths.append(Path(spec))
    out, names = [], set()
    for item in paths:
        if isinstance(item, Scene):
            fmt = item.format if item.format in FORMAT_PROTOCOL else "colmap"
            proto = protocol_for(item.path, fmt, protocol_set)
            scene, path = item.normalized(), item.path
        else:
            fmt = detect_format(item)
            proto = protocol_for(item, fmt, protocol_set)
            scene, path = load_at_resolution(item, proto.long_side, proto.background, fmt), item
        base = Path(path).name if path is not None else "scene"
        name, i = base, 1
        while name in names:  # e.g. the same seed from two synth:eval rigs
            i += 1
            name = f"{base}_{i}"
        names.add(name)
        out.append(EvalScene(name, scene, proto, path))
    return out
