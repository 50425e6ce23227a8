"""One policy for command outputs.

* :func:`check_writable` is called by every writing command before any work starts: an ``--out`` under
  an existing file, a path that is a folder where a file is expected (or the reverse), or a folder that
  cannot be written gives a one-line :class:`InputError` at once, not after minutes of work.
* Temporaries carry the writing process's id: ``.NAME.pidPID.XXXX`` (:func:`omnirecon.data.io.atomic_path`,
  viewer bundles) and ``.scene_NNNNN.tmpPID`` (synth). :func:`clean_stale` removes the ones whose
  process is gone (a ``kill -9`` or a power cut); the next run of a command calls it on its output folder.
* :func:`atomic_files` writes several files that belong together (a mesh as PLY + OBJ + GLB, its metrics
  and preview) to temporaries and renames them only when all are written, with Ctrl-C held back during
  the renames, so the set is the old one or the complete new one.
* :func:`claim` is how every writing verb takes its ``--out``: the path is checked (writable, neither
  inside nor holding an input), locked (one run per ``--out``: ``fcntl.flock`` on ``.NAME.lock`` beside
  it; a second run gets one line naming the first), and, for verbs whose output is a whole folder
  (``mode="replace"``: process, reconstruct, render, export, finetune, eval, lift, edit, pet, inspect and
  demo), built in ``.NAME.tmpPID`` and swapped in at the end (``renameat2(RENAME_EXCHANGE)`` where the
  kernel has it), so an interrupt leaves the old folder or the complete new one. A folder is only ever
  replaced when it holds the marker :data:`MARKER` that this tool writes into every output folder, and the
  replacement is said before any work starts. ``mode="fill"`` writes in place under the lock and marks a
  folder it created: ``train``, whose ``--resume`` continues the run folder (each checkpoint is a set
  renamed into place together, and ``checkpoints/latest`` moves only to a complete one), and ``synth``, whose
  folder grows by whole scenes (each built in ``.scene_NNNNN.tmpPID`` and renamed; existing scenes are kept).
  ``mesh`` writes a set of files (:func:`atomic_files`) under ``mode="file"``.
* Files are never lost either. ``mode="file"`` (``mesh``, ``bench``) locks every file of the set and refuses
  one that exists unless this tool wrote it (a record ``.NAME.omnirecon.json`` beside it names its inode, size
  and time: :func:`written_here`) or ``--overwrite`` is given; the files the run wrote get their record. The
  marker of a folder lists the files written into it: a folder is replaced only when everything in it is
  listed there or written here, and ``mode="fill"`` refuses a non-empty folder without the marker (a user's).
  ``mode="resume"`` (reconstruct) is
  ``"replace"`` with a work folder that outlives a failure: ``NAME.partial`` beside ``--out``
  (:func:`partial_folder`), kept when the run recorded a finished stage in it (:data:`PARTIAL`), reused by the next
  run, swapped in whole when complete.
* A record written in a temporary folder must name the final paths: before the swap,
  :func:`relative_records` rewrites every JSON file's paths into the temporary folder as paths relative
  to it (so they hold for ``--out``).

Size: the whole output policy (checks, lock, marker, swap) in one module, so that every verb
follows the same rules.
"""

from __future__ import annotations

import ctypes
import fcntl
import json
import os
import re
import shutil
import signal
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from omnirecon.errors import InputError
from omnirecon.records import real, relative_records, relative_to  # noqa: F401  (relative_to: part of this API)

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
        with held_signals():
            for tmp, p in zip(tmps, finals):
                os.replace(tmp, p)
    finally:
        for tmp in tmps:
            if tmp.exists():
                tmp.unlink()


def prepare_out(*paths: Path | None, kind: str = "folder", recursive: bool = False) -> None:
    """:func:`check_writable` on each output path (``None``, a default under ``outputs/``: that folder is
    checked) and :func:`clean_stale` on its folder. Checks only: writing verbs take their ``--out`` with
    :func:`claim`, which runs these checks too."""
    for path in paths or (None,):
        path = Path("outputs") if path is None else Path(path)
        check_writable(path, "folder" if path.name == "outputs" and not path.suffix else kind)
        clean_stale(path if kind == "folder" else path.parent, recursive)


# ------------------------------------------------------------------------------------------------ folders we own
MARKER = ".omnirecon-output.json"
"""Written into every output folder: ``{"tool": "omnirecon", "command": ..., "written": ...}``. Only a folder
holding it is ever replaced."""


@contextmanager
def held_signals():
    """Hold back Ctrl-C / SIGTERM / SIGHUP for the block (a few renames): delivered right after it."""
    sigs = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    except (AttributeError, OSError, ValueError):
        old = None
    try:
        yield
    finally:
        if old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def check_outside_inputs(out: Path, inputs, flag: str = "--out") -> None:
    """Refuse an output that is an input, lies inside one or holds one (a replaced or filled ``--out`` would
    change or delete the inputs)."""
    o = real(out)
    for given in inputs:
        if given is None or not os.path.lexists(given):  # a name such as synth:eval, or a missing path: not harmed
            continue
        i = real(given)
        if o == i or i in o.parents:
            raise InputError(f"{flag} is inside the input {given}", out,
                             f"write {flag} somewhere outside {given}, e.g. beside it")
        if o in i.parents:
            raise InputError(f"{flag} holds the input {given}", out,
                             f"choose a new folder for {flag} that does not contain {given}")


def check_out(path: Path, kind: str, inputs=(), flag: str = "--out") -> None:
    """:func:`check_writable` and :func:`check_outside_inputs` for one output path."""
    check_writable(path, kind, flag)
    check_outside_inputs(path, inputs, flag)


def file_record(path: Path) -> Path:
    """Where the record of a file this tool wrote lives: ``.NAME.omnirecon.json`` beside it."""
    path = Path(path)
    return path.parent / f".{path.name}.omnirecon.json"


def _stamp(path: Path) -> list[int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return [st.st_ino, st.st_size, st.st_mtime_ns]


def written_here(path: Path) -> bool:
    """Whether the file at ``path`` is the one this tool wrote there (its record names the same inode, size and
    modification time: a file the user put or edited there since is not)."""
    try:
        rec = json.loads(file_record(path).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(rec, dict) and rec.get("tool") == "omnirecon" and rec.get("stamp") == _stamp(path)


def record_file(path: Path, command: str) -> None:
    """Record the file ``path`` as written by ``command`` (see :func:`written_here`)."""
    rec = file_record(path)
    tmp = rec.parent / f".{path.name}.omnirecon.pid{os.getpid()}.json"
    tmp.write_text(json.dumps({"tool": "omnirecon", "command": command, "stamp": _stamp(path),
                               "written": time.strftime("%Y-%m-%d %H:%M:%S %Z")}))
    os.replace(tmp, rec)


def remove_written(path: Path) -> bool:
    """Delete the file ``path`` and its record only when this tool wrote it; True when deleted."""
    if not written_here(path):
        return False
    Path(path).unlink(missing_ok=True)
    file_record(path).unlink(missing_ok=True)
    return True


def check_replaceable(paths, overwrite: bool = False, flag: str = "--out") -> None:
    """Refuse (InputError) an existing file among ``paths`` that this tool did not write, unless ``overwrite``."""
    for path in paths:
        if not overwrite and os.path.lexists(path) and not written_here(path):
            raise InputError("exists and was not written by omnirecon: it is never replaced without --overwrite",
                             Path(path), f"choose another {flag}, or add --overwrite to replace it")


def read_marker(folder: Path) -> dict | None:
    """The marker of an output folder written by this tool, else ``None``."""
    try:
        m = json.loads((Path(folder) / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return m if isinstance(m, dict) and m.get("tool") == "omnirecon" and isinstance(m.get("command"), str) else None


def _contents(folder: Path) -> list[str]:
    """Every file and link under ``folder`` (relative, sorted), but the marker and our temporaries."""
    out = []
    for dirpath, _, files in os.walk(folder):
        for n in files:
            if n != MARKER and not STALE.match(n):
                out.append(os.path.relpath(os.path.join(dirpath, n), folder))
    return sorted(out)


def write_marker(folder: Path, command: str) -> None:
    folder = Path(folder)
    tmp = folder / f".{MARKER.lstrip('.')}.pid{os.getpid()}"
    tmp.write_text(json.dumps({"tool": "omnirecon", "command": command,
                               "written": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "files": _contents(folder)}))
    os.replace(tmp, folder / MARKER)


def foreign_files(folder: Path, marker: dict) -> list[str]:
    """Files in an output folder that its marker does not list and no record says this tool wrote (a user's
    additions: never deleted). A marker of an older version without the list lists nothing to check."""
    listed = marker.get("files")
    if not isinstance(listed, list):
        return []
    listed = set(listed)
    return [f for f in _contents(folder) if f not in listed and not Path(f).name.endswith(".omnirecon.json")
            and not written_here(Path(folder) / f)]


def describe(marker: dict) -> str:
    return f"an omnirecon {marker['command']} output written {marker.get('written', '(time unknown)')}"


def _mkdirs(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; returns the ones created (outermost first)."""
    missing = []
    while not folder.exists():
        missing.append(folder)
        folder = folder.parent
    created = []
    for d in reversed(missing):
        try:
            d.mkdir()
            created.append(d)
        except FileExistsError:
            pass
    return created


def _rmdirs(created: list[Path]) -> None:
    for d in reversed(created):
        try:
            d.rmdir()  # only when empty: what a failed run created and left unused
        except OSError:
            break


@contextmanager
def out_lock(out: Path, command: str, flag: str = "--out"):
    """Hold ``fcntl.flock`` on ``.NAME.lock`` beside ``out`` for the block; a second run on the same ``out``
    gets an InputError naming the first. The lock file goes at the end (a killed run's file holds no lock
    and is reused); parents created for it and left empty after a failure are removed."""
    out = Path(os.path.abspath(out))
    lockfile = out.parent / f".{out.name}.lock"
    created = _mkdirs(out.parent)
    try:
        while True:
            fd = os.open(lockfile, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                holder = os.read(fd, 200).decode(errors="replace").strip() or "another process"
                os.close(fd)
                raise InputError(f"another omnirecon run is writing {flag} ({holder})", out,
                                 f"wait for it to finish, or choose another {flag}") from None
            try:
                same = os.stat(lockfile).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:  # else the holder removed the file between our open and our lock: take the new one
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()}, omnirecon {command}".encode())
    except BaseException:
        _rmdirs(created)
        raise
    try:
        yield
    finally:
        try:
            os.unlink(lockfile)
        except OSError:
            pass
        os.close(fd)
        _rmdirs(created)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where unsupported."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    return fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0


def swap_in(new: Path, out: Path) -> None:
    """Put folder ``new`` at ``out``, replacing what is there as one step where the kernel allows (else two
    renames; :func:`restore_swapped` undoes a crash between them). Interrupts wait for it."""
    with held_signals():
        if not out.exists() and not out.is_symlink():
            os.rename(new, out)
            return
        if _exchange(new, out):
            old = new
        else:
            old = out.parent / f".{out.name}.old{os.getpid()}"
            os.rename(out, old)
            os.rename(new, out)
    shutil.rmtree(old, ignore_errors=True)


def restore_swapped(out: Path) -> None:
    """A run killed between :func:`swap_in`'s two renames left ``.NAME.oldPID`` and no ``NAME``: put it back."""
    if out.exists():
        return
    for old in out.parent.glob(f".{out.name}.old*"):
        pid = old.name[len(out.name) + 5:]
        if pid.isdigit() and not pid_alive(int(pid)):
            os.rename(old, out)
            return


@dataclass
class Claim:
    """A verb's hold on its output: write into ``work`` (``out`` itself, or its temporary twin)."""

    out: Path
    work: Path
    command: str
    replaced: str | None = None


@contextmanager
def claim(out: Path | None, command: str, *, inputs=(), mode: str = "fill", overwrite: bool | None = None,
          flag: str = "--out", recursive: bool = False, say=print, files=(), adopt: bool = False):
    """Take ``out`` for one run of ``command`` (see the module docstring); yields a :class:`Claim`.

    ``mode="replace"``: the run's output is the whole folder, built in ``claim.work`` and swapped in when
    the block succeeds. An existing non-empty ``out`` is replaced only when it holds :data:`MARKER` and
    either ``overwrite`` is True (verbs with ``--overwrite``; False refuses) or, for verbs without the flag
    (``overwrite=None``), the marker names the same command. ``mode="fill"``: ``claim.work == out``; a folder
    the run created gets the marker, and is removed again if the run fails and leaves it empty.
    ``mode="resume"``: as ``"replace"``, built in :func:`partial_folder` (``NAME.partial``), which the block's
    failure leaves in place when a stage finished in it (:func:`kept_stages`) and the next run reuses.
    ``mode="file"``: ``out`` is a file, with the other files of its set in ``files``: each is checked, locked
    and refused when it exists and this tool did not write it (unless ``overwrite``); those the block wrote
    (changed) are recorded as written here.
    ``out=None`` (a verb's default under ``outputs/``): ``outputs/<command>`` is claimed in fill mode.
    ``recursive``: also remove stale temporaries anywhere inside ``out`` (run folders with checkpoints).
    ``adopt``: fill a non-empty folder without the marker too (``train --resume`` of a run folder written by a
    version before the marker)."""
    if out is None:
        out, mode = Path("outputs") / command, "fill"
    out = Path(out)
    check_out(out, "file" if mode == "file" else "folder", inputs, flag)
    if mode == "resume":
        check_out(partial_folder(out), "folder", inputs, f"{flag}'s work folder")
    if mode in ("replace", "resume") and real(out) in (real(Path.cwd()), *real(Path.cwd()).parents):
        raise InputError(f"{flag} is the working folder or holds it, and {command} replaces its {flag} whole", out,
                         f"choose a new folder for {flag}, e.g. {flag} {command}_out")
    if mode == "file":
        with claim_files([out, *files], command, inputs, bool(overwrite), flag):
            yield Claim(out, out, command)
        return
    with out_lock(out, command, flag):
        clean_stale(out.parent)  # a killed run's temporaries beside out (their process is gone)
        restore_swapped(out)
        clean_stale(out, recursive)
        existed = out.is_dir() and any(out.iterdir())
        marker = read_marker(out) if existed else None
        if mode == "fill":
            if existed and marker is None and not adopt:
                raise InputError(f"{flag} holds files this tool did not write (no {MARKER}): it never writes there",
                                 out, f"choose a new or empty folder for {flag}")
            created = not out.exists()
            try:
                yield Claim(out, out, command)
            except BaseException:
                if created and out.is_dir() and not any(out.iterdir()):
                    out.rmdir()
                raise
            if out.is_dir() and (marker is not None or not existed):
                write_marker(out, command)
            return
        replaced = _replacing(out, existed, marker, overwrite, command, flag, say)
        if mode == "resume":
            yield from _resumable(out, command, replaced, flag)
            return
        tmp = out.parent / f".{out.name}.tmp{os.getpid()}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        try:
            yield Claim(out, tmp, command, replaced)
            relative_records(tmp)
            write_marker(tmp, command)
            swap_in(tmp, out)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


@contextmanager
def claim_files(paths, command: str, inputs=(), overwrite: bool = False, flag: str = "--out"):
    """``claim``'s ``mode="file"``: lock every file of the set (sorted: two runs sharing any file cannot both
    proceed), refuse one this tool did not write (:func:`check_replaceable`), record those the block wrote."""
    from contextlib import ExitStack

    paths = sorted({Path(os.path.abspath(p)) for p in paths})
    for p in paths:
        check_out(p, "file", inputs, flag)
    with ExitStack() as stack:
        for p in paths:
            stack.enter_context(out_lock(p, command, flag))
        clean_stale(paths[0].parent)  # a killed run's temporaries beside out (their process is gone)
        check_replaceable(paths, overwrite, flag)
        before = {p: _stamp(p) for p in paths}
        yield
        for p in paths:
            if os.path.isfile(p) and not os.path.islink(p) and _stamp(p) != before[p]:
                record_file(p, command)


def _replacing(out: Path, existed: bool, marker: dict | None, overwrite: bool | None, command: str, flag: str,
               say) -> str | None:
    """The policy for an existing ``out`` of a verb that replaces it whole (see :func:`claim`): refuses, or returns
    what will be replaced (said at once), or None when nothing is."""
    if overwrite is False and out.exists():
        raise InputError("output folder already exists", out, f"choose another {flag}, or add --overwrite")
    if not existed:
        return None
    if marker is None:
        raise InputError(f"{flag} holds files this tool did not write (no {MARKER}): it is never replaced",
                         out, f"choose a new or empty folder for {flag}")
    if overwrite is None and marker["command"] != command:
        raise InputError(f"{flag} holds {describe(marker)}", out, f"choose another {flag} for {command}")
    foreign = foreign_files(out, marker)
    if foreign:
        raise InputError(f"{flag} holds {foreign[0]}, which this tool did not write: it is never deleted",
                         out / foreign[0], f"move it out of {out}, or choose another {flag}")
    replaced = describe(marker)
    say(f"replacing {out}: {replaced} (the new one takes its place when complete)")
    return replaced


# ------------------------------------------------------------------------------------------ resumable work folders
PARTIAL = ".omnirecon-partial"
"""The folder a resumable run keeps in its work folder (:func:`partial_folder`): ``stages.json``, the finished stages'
records, and what they hand to the next run (:class:`omnirecon.workflows.stages.Stages`). A work folder is reused
or removed only when it holds this folder or :data:`MARKER` (a run killed while it finished)."""


def partial_folder(out: Path) -> Path:
    """The resumable work folder of ``out``: ``NAME.partial`` beside it."""
    out = Path(out)
    return out.parent / f"{out.name}.partial"


def kept_stages(work: Path) -> list[str]:
    """The stages a resumable run recorded as finished in ``work`` (none when there is no record)."""
    try:
        stages = json.loads((Path(work) / PARTIAL / "stages.json").read_text()).get("stages", {})
    except (OSError, ValueError, AttributeError, RecursionError):
        return []
    return list(stages) if isinstance(stages, dict) else []


def _resumable(out: Path, command: str, replaced: str | None, flag: str):
    """``claim(mode="resume")``'s work folder: reused when a run left it, kept after a failure when a stage finished
    in it, else removed; when the block succeeds, its resume record goes and it is swapped in at ``out``."""
    work = partial_folder(out)
    if work.is_symlink() or (work.exists() and not work.is_dir()) or (work / PARTIAL).is_symlink():
        raise InputError(f"{flag}'s work folder {work.name} exists and is not a folder (or its {PARTIAL} is a link)",
                         work, f"move it away, or choose another {flag}")
    if work.is_dir() and any(work.iterdir()) and not (work / PARTIAL).is_dir() and read_marker(work) is None:
        raise InputError(f"{flag}'s work folder holds files this tool did not write (no {PARTIAL}): it is never "
                         "replaced", work, f"move it away, or choose another {flag}")
    work.mkdir(exist_ok=True)
    try:
        yield Claim(out, work, command, replaced)
    except BaseException:
        if not kept_stages(work):
            shutil.rmtree(work, ignore_errors=True)  # nothing finished: nothing to keep
        raise
    write_marker(work, command)  # first: a run killed from here on leaves a folder that is still ours
    shutil.rmtree(work / PARTIAL, ignore_errors=True)
    relative_records(work)
    swap_in(work, out)
