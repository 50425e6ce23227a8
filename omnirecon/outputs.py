"""One policy for command outputs.

* :func:`check_writable` is called by every writing command before any work starts: an ``--out`` under
  an existing file, a path that is a folder where a file is expected (or the reverse), or a folder that
  cannot be written gives a one-line :class:`InputError` at once, not after minutes of work.
* Temporaries carry the writing process's id: ``.NAME.pidPID.XXXX`` (:func:`omnirecon.data.io.atomic_path`,
  viewer bundles) and ``.scene_NNNNN.tmpPID`` (synth). :func:`clean_stale` removes the ones whose
  process is gone (a ``kill -9`` or a power cut); the next run of a command calls it on its output folder.
* :func:`atomic_files` writes several files that belong together (a mesh as PLY + OBJ + GLB) to
  temporaries and renames them only when all are written, so the set is complete or absent.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

from omnirecon.errors import InputError

# .NAME.pid123.abc.ext (atomic_path), .viewer.pid123.abc/ (bundles), .scene_00001.tmp123/ (synth)
STALE = re.compile(r"^\..+\.(?:pid|tmp)(\d+)(?:\..*)?$")


def check_writable(path: Path | None, kind: str = "folder", flag: str = "--out") -> None:
    """Refuse (InputError) an output ``path`` that cannot be written: ``kind`` is ``"folder"`` (the
    command creates or fills the folder ``path``) or ``"file"`` (it writes the file ``path``). Creates
    nothing; probes the nearest existing folder with a temporary file that it removes."""
    if path is None:
        return
    path = Path(path)
    if kind == "folder" and path.exists() and not path.is_dir():
        raise InputError(f"{flag} exists and is not a folder", path, f"pass a folder (new or existing) for {flag}")
    if kind == "file" and path.is_dir():
        raise InputError(f"{flag} is a folder", path, f"pass a file name for {flag}, e.g. {path / 'out'}")
    probe = path if kind == "folder" else path.parent
    probe = Path(os.path.abspath(probe))
    while not probe.exists():
        if probe.is_symlink():
            raise InputError(f"{flag} goes through a dangling link", probe, "fix the link or choose another path")
        probe = probe.parent
    if not probe.is_dir():
        raise InputError(f"cannot create {flag} under a file", probe,
                         f"choose a {flag} path that is not inside the file {probe.name}")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".omnirecon-write-test.pid{os.getpid()}.", dir=probe)
    except OSError as e:
        raise InputError(f"cannot write in {probe} ({e.strerror or type(e).__name__})", path,
                         f"choose a writable {flag}, or fix the folder's permissions") from e
    os.close(fd)
    os.unlink(tmp)


def pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    except OverflowError:
        return False
    return True


def clean_stale(folder: Path | None, recursive: bool = False) -> list[Path]:
    """Remove temporaries of our naming (see the module docstring) in ``folder`` whose process is dead;
    returns what was removed. Never touches other names or live processes' temporaries."""
    if folder is None or not Path(folder).is_dir():
        return []
    removed = []
    entries = Path(folder).rglob(".*") if recursive else Path(folder).glob(".*")
    for p in sorted(entries, key=lambda q: len(q.parts), reverse=True):
        m = STALE.match(p.name)
        if not m or pid_alive(int(m.group(1))):
            continue
        try:
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
            removed.append(p)
        except FileNotFoundError:
            pass
        except OSError:
            continue  # not ours to fight over (permissions): the next run tries again
    return removed


@contextmanager
def atomic_files(paths):
    """Yield one temporary path per entry of ``paths`` (same folder, hidden, tagged with our PID); when the
    block succeeds, rename them onto ``paths`` one after the other (all written first: a crash leaves
    the previous set or none, never a mix with missing members); on failure remove them."""
    finals = [Path(p) for p in paths]
    tmps = []
    umask = os.umask(0)
    os.umask(umask)
    try:
        for p in finals:
            p.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{p.stem}.pid{os.getpid()}.", suffix=p.suffix, dir=p.parent)
            os.close(fd)
            tmps.append(Path(tmp))
        yield list(tmps)
        for tmp in tmps:
            os.chmod(tmp, 0o666 & ~umask)
        for tmp, p in zip(tmps, finals):
            os.replace(tmp, p)
    finally:
        for tmp in tmps:
            if tmp.exists():
                tmp.unlink()


def prepare_out(*paths: Path | None, kind: str = "folder", recursive: bool = False) -> None:
    """What every writing command calls first: :func:`check_writable` on each output path (``None``, a
    default under ``outputs/``: that folder is checked) and :func:`clean_stale` on its folder."""
    for path in paths or (None,):
        path = Path("outputs") if path is None else Path(path)
        check_writable(path, "folder" if path.name == "outputs" and not path.suffix else kind)
        clean_stale(path if kind == "folder" else path.parent, recursive)
