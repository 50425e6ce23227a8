"""A long run's finished stages, kept for the next run.

A resumable verb (``reconstruct``) builds its output in ``OUT.partial`` (:func:`omnirecon.outputs.claim`,
``mode="resume"``) and records each finished stage there, in ``.omnirecon-partial/stages.json``: what the stage
depended on (digests of the input files, the options that change its result), its record, and the files it wrote.
A failed or interrupted run leaves the folder; the next run of the command keeps every stage from the first on
whose dependencies are unchanged, removes whatever else is in the folder (a stage cut off half-way), and runs the
rest. Records go through JSON both when written and when kept, so a resumed run hands the later stages exactly what
an uninterrupted one does.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import trimesh

from omnirecon.data.io import write_json
from omnirecon.outputs import PARTIAL


def files_digest(path: Path | None) -> str | None:
    """A digest of the files at ``path`` (a file, or every file under a folder): their names, sizes and modification
    times, so an edited, added or removed file changes it; ``None`` for no path."""
    if path is None:
        return None
    path = Path(path)
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    h = hashlib.sha1()
    for f in files:
        try:
            st = f.stat()
        except OSError:  # unreadable or gone: the stage that reads it says so
            continue
        h.update(f"{f.relative_to(path) if f != path else f.name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


class Stages:
    """The finished stages of a run in ``work`` (its resumable work folder).

    ``depends``: each stage's name, in run order, with what its result depends on (JSON values, keyed by what a
    user would call them: ``"--frames"``, ``"PATH's files"``); a later stage depends on the earlier ones too.
    ``resume=False`` keeps nothing. ``say`` prints the one-line note on what is kept.
    """

    def __init__(self, work: Path, depends: dict[str, dict], resume: bool = True, say=print):
        self.work = Path(work)
        self.folder = self.work / PARTIAL
        self.depends = depends
        self.kept: dict[str, dict] = self._load(resume, say)
        self.current: str | None = None
        """The stage running (a failure names it)."""
        self.folder.mkdir(exist_ok=True)
        self._write()

    def discard(self) -> None:
        """Keep nothing for the next run: the record goes (and with it the claim's reason to keep the folder)."""
        shutil.rmtree(self.folder, ignore_errors=True)

    def _load(self, resume: bool, say) -> dict[str, dict]:
        try:
            old = json.loads((self.folder / "stages.json").read_text()).get("stages", {})
        except (OSError, ValueError, AttributeError, RecursionError):  # garbage (deep JSON): nothing kept
            old = {}
        old = old if isinstance(old, dict) else {}
        kept, changed = {}, []
        for name, depends in self.depends.items():
            record = old.get(name) if resume else None
            if not isinstance(record, dict):
                break
            if record.get("depends") != depends:
                changed = [k for k in depends if record.get("depends", {}).get(k) != depends[k]]
                break
            kept[name] = record
        if old and not resume:
            say(f"starting over in {self.work} (--no-resume): the stages an earlier run kept there go")
        elif changed:
            say(f"{' and '.join(changed)} changed since the run that kept {self.work}: "
                + (f"keeping {', '.join(kept)}, running the rest" if kept else "starting over"))
        elif kept:
            say(f"continuing from {self.work}: {', '.join(kept)} kept from an earlier run (--no-resume starts over)")
        self._remove_unkept(kept)
        return kept

    def _remove_unkept(self, kept: dict[str, dict]) -> None:
        """Everything in the work folder that no kept stage wrote: the files of a stage cut off half-way."""
        owned = {f for record in kept.values() for f in record.get("files", [])}
        for p in self.work.iterdir():
            if p.name not in owned and p.name != PARTIAL:
                shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
        for p in self.folder.iterdir() if self.folder.is_dir() else []:
            if p.name != "stages.json" and p.name.split(".")[0] not in kept:
                shutil.rmtree(p) if p.is_dir() else p.unlink()

    def _write(self) -> None:
        write_json(self.folder / "stages.json", {"stages": self.kept})  # atomic: the old record or the new one

    def result(self, name: str) -> dict | None:
        """The kept record of stage ``name``, or None when it runs."""
        return self.kept[name]["result"] if name in self.kept else None

    def measured(self, name: str) -> dict[str, float]:
        """What the kept stage ``name`` measured when it ran (``seconds``, ``cpu_seconds``, ``peak_rss_mb``)."""
        return self.kept[name].get("measured", {})

    def finish(self, name: str, result: dict, measured: dict | None = None) -> dict:
        """Record stage ``name`` as finished with ``result`` (JSON-serialisable) and the files it added to the work
        folder; returns ``result`` as the next run reads it back."""
        owned = {f for other, record in self.kept.items() if other != name for f in record.get("files", [])}
        files = sorted(p.name for p in self.work.iterdir() if p.name not in owned and p.name != PARTIAL)
        result = json.loads(json.dumps(result))
        self.kept[name] = {"depends": self.depends[name], "result": result, "files": files,
                           "measured": measured or {}}
        self._write()
        return result

    def mesh_path(self, name: str) -> Path:
        """Where stage ``name`` keeps its meshes for the next run (:meth:`keep_meshes`)."""
        return self.folder / f"{name}.meshes.npz"

    def keep_meshes(self, name: str, meshes: dict[str, trimesh.Trimesh]) -> None:
        """Write ``meshes`` (vertices and faces, exact) for the next run; every run goes on with them as read back
        (:meth:`meshes`), so a resumed run and an uninterrupted one go on alike."""
        path = self.mesh_path(name)
        tmp = path.with_name(f".{path.name}.pid{os.getpid()}.npz")
        np.savez(tmp, **{f"{k}.{part}": getattr(m, part) for k, m in meshes.items() for part in ("vertices", "faces")})
        os.replace(tmp, path)

    def meshes(self, name: str) -> dict[str, trimesh.Trimesh]:
        """The meshes stage ``name`` kept (:meth:`keep_meshes`)."""
        with np.load(self.mesh_path(name)) as z:
            keys = sorted({k.split(".")[0] for k in z.files})
            return {k: trimesh.Trimesh(z[f"{k}.vertices"], z[f"{k}.faces"], process=False) for k in keys}


class StageRunner:
    """``run(name, stage)``: the record ``stages`` kept of stage ``name`` from an earlier run, else ``stage(said)``'s
    (``said``: the lines it prints), kept as finished with ``lap``'s measurements of it; either way the stage's lines join
    ``lines`` and ``lap`` closes the stage. ``resumed``: the kept stages' seconds when they ran."""

    def __init__(self, stages: Stages, lap, lines: list[str]):
        self.stages, self.lap, self.lines = stages, lap, lines
        self.resumed: dict[str, float] = {}

    def __call__(self, name: str, stage) -> dict:
        self.stages.current = name
        kept = self.stages.result(name)
        if kept is None:
            said: list[str] = []
            result = stage(said)
            kept = self.stages.finish(name, {**result, "said": said}, self.lap(name))
        else:
            self.lap(name)
            self.resumed[name] = self.stages.measured(name).get("seconds", 0.0)
        self.lines += kept["said"]
        return kept
