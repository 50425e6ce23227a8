"""Interrupts, kills and concurrent runs (issue 28 items 1 and 7): a verb whose output is a folder builds it
beside ``--out`` and swaps it in whole, so Ctrl-C or ``kill -9`` at any moment leaves the previous folder
byte for byte (or none), a second run on the same ``--out`` is refused while the first holds it, and the next
run cleans what a killed one left. In-process cases interrupt inside the run; the subprocess cases send real
signals to a real ``omnirecon`` process."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from omnirecon.outputs import MARKER, claim, write_marker
from tests.data.test_bad_input import blender_scene, ring_gl

ROOT = Path(__file__).resolve().parents[2]
CK = ROOT / "checkpoints" / "omnirecon-tiny"
RENDER = ["--model", "floor", "--resolution", "8", "--num-views", "2", "--no-video", "--device", "cpu",
          "--threads", "1"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return blender_scene(tmp_path_factory.mktemp("interrupts") / "scene", mats=ring_gl(6).tolist())


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _previous(out: Path, verb: str) -> dict[str, bytes]:
    """A complete earlier output of ``verb`` at ``out`` (marked, so a new run may replace it)."""
    with claim(out, verb, mode="replace") as c:
        (c.work / "old.txt").write_text(f"an earlier {verb} run")
    return _files(out)


# verb -> (arguments, the module attribute the run reaches after taking --out)
VERBS = {
    "lift": (["lift", "--ckpt", CK, "--scene", "{scene}", "--threads", "1"], "omnirecon.workflows.lift.prepare_scenes"),
    "edit": (["edit", "--ckpt", CK, "--scene", "{scene}", "--label", "1", "--threads", "1"],
             "omnirecon.workflows.edit.prepare_scenes"),
    "pet": (["pet", "--ckpt", CK, "--scene", "{scene}", "--threads", "1"], "omnirecon.workflows.pet.prepare_scenes"),
    "inspect": (["inspect", "{scene}"], "omnirecon.workflows.inspect.load_scene"),
    "eval": (["eval", "--model", "floor", "--scenes", "{scene}", "--threads", "1"], "omnirecon.commands.eval.evaluate"),
    "demo": (["demo", "--quick", "--data", "{scene}", "--threads", "1"], "omnirecon.workflows.demo.demo_scene"),
}


@pytest.mark.parametrize("verb", sorted(VERBS))
def test_ctrl_c_mid_run_keeps_the_previous_output_whole(verb, scene, tmp_path, run_cli, monkeypatch):
    """Ctrl-C after the run has written part of its new output: exit 130, ``--out`` exactly as before, no
    temporary left (the verbs that wrote in place before issue 28: eval, lift, edit, pet, inspect, demo)."""
    out = tmp_path / "o"
    before = _previous(out, verb)
    args, where = VERBS[verb]

    def interrupted(*_, **__):
        (work,) = tmp_path.glob(".o.tmp*")  # the new output, being built beside --out
        (work / "half_written.png").write_bytes(b"part of a new output")
        raise KeyboardInterrupt

    monkeypatch.setattr(where, interrupted)
    code, stdout, err = run_cli([a.format(scene=scene) if isinstance(a, str) else a for a in args] + ["--out", out])
    assert code == 130, err
    assert f"replacing {out}: an omnirecon {verb} output" in stdout
    assert _files(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o"], "temporaries or lock left beside --out"


def test_a_new_inspect_replaces_the_old_folder_whole(scene, tmp_path, run_cli):
    """A finished run leaves only its own files: a stale member of the previous output goes."""
    out = tmp_path / "i"
    code, _, err = run_cli(["inspect", scene, "--out", out])
    assert code == 0, err
    (out / "stale.png").write_bytes(b"from an earlier run")
    write_marker(out, "inspect")  # listed by the earlier run's marker (a file the user added is never deleted)
    code, stdout, err = run_cli(["inspect", scene, "--out", out])
    assert code == 0, err
    assert f"replacing {out}: an omnirecon inspect output" in stdout
    assert "wrote" in stdout and ".tmp" not in stdout  # the message names --out, not the folder it was built in
    assert sorted(p.name for p in out.iterdir()) == sorted([MARKER, "cameras.png", "epipolar.png", "summary.json"])
    assert ".tmp" not in (out / "summary.json").read_text()


def _terminal_signals() -> None:
    """The child starts as a terminal's foreground command: Ctrl-C at its default. A suite launched as a background
    job (``make test &``) ignores SIGINT, children inherit that, and Python then installs no KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(args: list, cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "omnirecon.cli", *map(str, args)], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_terminal_signals)


def _wait_for(pattern: str, folder: Path, proc: subprocess.Popen, seconds: float = 180) -> list[Path]:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        found = sorted(folder.glob(pattern))
        if found:
            return found
        if proc.poll() is not None:
            pytest.fail(f"the run ended before {pattern} appeared: {proc.communicate()[1][-2000:]}")
        time.sleep(0.05)
    proc.kill()
    pytest.fail(f"{pattern} did not appear in {seconds} s")


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_render_killed_mid_run_keeps_the_previous_frames(sig, scene, tmp_path, run_cli):
    """``kill -9`` (or Ctrl-C) while a render writes its frames: the previous frames stay as they were; after
    ``kill -9`` the next run removes the dead run's temporary folder and replaces the output whole."""
    out = tmp_path / "r"
    code, _, err = run_cli(["render", "--scene", scene, "--out", out, "--frames", "2", *RENDER])
    assert code == 0, err
    before = _files(out)
    proc = _start(["render", "--scene", scene, "--out", out, "--frames", "100000", *RENDER], tmp_path)
    _wait_for(".r.tmp*/frames/0001.png", tmp_path, proc)
    proc.send_signal(sig)
    proc.communicate(timeout=120)
    assert proc.returncode == (-signal.SIGKILL if sig == signal.SIGKILL else 130)
    assert _files(out) == before
    left = sorted(p.name for p in tmp_path.iterdir() if p.name != "r")
    assert (left == []) if sig == signal.SIGINT else all(n.startswith((".r.tmp", ".r.lock")) for n in left), left
    code, stdout, err = run_cli(["render", "--scene", scene, "--out", out, "--frames", "1", *RENDER])
    assert code == 0 and "replacing" in stdout, err
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["0000.png"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"]


def test_two_concurrent_renders_to_one_out(scene, tmp_path):
    """Two real processes on one --out: the second is refused at once with one line naming the first; the
    first's output is complete when it ends (here: interrupted, so the folder is as before, i.e. absent)."""
    out = tmp_path / "r"
    first = _start(["render", "--scene", scene, "--out", out, "--frames", "100000", *RENDER], tmp_path)
    _wait_for(".r.tmp*/frames/0000.png", tmp_path, first)
    second = _start(["render", "--scene", scene, "--out", out, "--frames", "2", *RENDER], tmp_path)
    _, err = second.communicate(timeout=300)
    assert second.returncode == 2 and len(err.strip().splitlines()) == 1, err
    assert f"another omnirecon run is writing --out (pid {first.pid}, omnirecon render)" in err
    first.send_signal(signal.SIGINT)
    first.communicate(timeout=120)
    assert first.returncode == 130
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.slow
def test_reconstruct_killed_mid_run_keeps_the_previous_output(scene, tmp_path):
    """``kill -9`` of ``reconstruct --overwrite`` once its new mesh is written: the previous output stands byte
    for byte."""
    out = tmp_path / "rec"
    before = _previous(out, "reconstruct")
    proc = _start(["reconstruct", scene, "--out", out, "--overwrite", "--ckpt", CK, "--resolution", "16",
                   "--mesh-resolution", "16", "--finetune-seconds", "30", "--frames", "2", "--no-viewer",
                   "--threads", "1"], tmp_path)
    _wait_for("rec.partial/mesh.ply", tmp_path, proc, seconds=600)
    proc.kill()
    proc.communicate(timeout=120)
    assert _files(out) == before


def test_an_interrupted_checkpoint_save_leaves_the_previous_checkpoint(tmp_path, monkeypatch):
    """``train`` continues its folder (never replaced), so each checkpoint is the set unit: weights, optimizer
    state and meta.json are renamed into place together, and Ctrl-C while writing the set (here: at meta.json,
    the last member) leaves the previous checkpoint's files byte for byte."""
    import torch

    from omnirecon.engine import checkpoint
    from omnirecon.models.registry import build_model

    model = build_model("gpnr-tiny")
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    folder = tmp_path / "step_0000001"
    checkpoint.save_checkpoint(folder, model, "gpnr-tiny", 1, opt)
    before = _files(folder)
    with torch.no_grad():
        next(model.parameters()).add_(1.0)

    def interrupted(*_, **__):
        raise KeyboardInterrupt

    monkeypatch.setattr(checkpoint, "write_json", interrupted)
    with pytest.raises(KeyboardInterrupt):
        checkpoint.save_checkpoint(folder, model, "gpnr-tiny", 2, opt)
    assert _files(folder) == before
    monkeypatch.undo()
    checkpoint.save_checkpoint(folder, model, "gpnr-tiny", 2, opt)
    assert checkpoint.read_meta(folder)["step"] == 2 and sorted(_files(folder)) == sorted(before)
