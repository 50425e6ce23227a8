"""Cases of issue 20 that need more than the malformed-input table: resume from the newest intact
checkpoint, the output policy (writability checked first, stale temporaries removed, multi-file outputs
complete or absent), ``--verbose`` and the memory-based ``--chunk`` default."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from omnirecon.cli import main
from omnirecon.engine.checkpoint_check import resume_folder
from omnirecon.errors import InputError
from omnirecon.outputs import MARKER, atomic_files, check_writable, clean_stale, write_marker
from tests.data.test_bad_input import blender_scene, ring_gl

TRAIN = ["--model", "gpnr-tiny", "--model-overrides", "num_samples=8", "dim=32", "mlp_dim=32", "heads=1",
         "layers=[1,1,1]", "point_freqs=4", "--num-views", "2", "--resolution", "8", "--rays", "16", "--warmup", "1",
         "--log-every", "1", "--val-every", "0", "--threads", "1", "--no-progress"]


def dead_pid() -> int:
    """A process id that is not running (a child that has exited and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


# ---------------------------------------------------------------------- resume
@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    """A 4-step run with checkpoints at steps 2 and 4 (latest -> step_0000004), on a 6-view 8x8 scene."""
    root = tmp_path_factory.mktemp("resume")
    scene = blender_scene(root / "scene", mats=ring_gl(6).tolist())
    run = root / "run"
    args = ["train", "--data", str(scene), "--out", str(run), "--cache", str(root / "cache"), *TRAIN]
    assert main([*args, "--steps", "6", "--stop-at", "4", "--ckpt-every", "2", "--keep", "2"]) == 0
    assert {"latest", "step_0000002", "step_0000004"} <= {p.name for p in (run / "checkpoints").iterdir()}
    return {"run": run, "args": args}


def _copy(run_folder, tmp_path) -> Path:
    run = tmp_path / "run"
    shutil.copytree(run_folder["run"], run, symlinks=True)
    return run


def _resume(run_folder, run: Path, capsys) -> tuple[int, str]:
    args = [a if a != str(run_folder["run"]) else str(run) for a in run_folder["args"]]
    capsys.readouterr()
    rc = main([*args, "--steps", "6", "--resume", "--ckpt-every", "2", "--keep", "2"])
    return rc, capsys.readouterr().err


@pytest.mark.parametrize("damage", ["dangling", "truncated_model", "missing_optimizer", "truncated_meta"])
def test_resume_uses_the_newest_intact_checkpoint(run_folder, tmp_path, capsys, damage):
    run = _copy(run_folder, tmp_path)
    ck = run / "checkpoints"
    if damage == "dangling":
        (ck / "latest").unlink()
        os.symlink("step_0000009", ck / "latest")
        shutil.rmtree(ck / "step_0000004")
        expect = "step_0000002"
    else:
        f = {"truncated_model": "model.safetensors", "missing_optimizer": "optimizer.safetensors",
             "truncated_meta": "meta.json"}[damage]
        target = ck / "step_0000004" / f
        if damage == "missing_optimizer":
            target.unlink()
        else:
            target.write_bytes(target.read_bytes()[: target.stat().st_size // 2])
        expect = "step_0000002"
    assert resume_folder(run) == ck / expect
    rc, err = _resume(run_folder, run, capsys)
    assert rc == 0, err
    assert f"resuming from the newest intact checkpoint, {expect}" in " ".join(err.split()), err
    steps = [json.loads(ln)["step"] for ln in (run / "metrics.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3, 4, 5, 6], steps  # lines after step 2 dropped, then 3..6 trained again
    assert json.loads((ck / "latest" / "meta.json").read_text())["step"] == 6


def test_resume_refuses_when_nothing_is_intact(run_folder, tmp_path, capsys):
    run = _copy(run_folder, tmp_path)
    for step in ("step_0000002", "step_0000004"):
        f = run / "checkpoints" / step / "model.safetensors"
        f.write_bytes(f.read_bytes()[:100])
    rc, err = _resume(run_folder, run, capsys)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and "checkpoints/latest" in lines[0] and "unreadable" in lines[0], err
    assert "(fix: " in lines[0]
    assert "missing" not in lines[0]  # a truncated file is unreadable, not missing


def test_intact_latest_is_used_without_a_note(run_folder):
    assert resume_folder(run_folder["run"]) == run_folder["run"] / "checkpoints" / "latest"
    notes: list[str] = []
    resume_folder(run_folder["run"], notes)
    assert notes == []


# ---------------------------------------------------------------------- output policy
def test_check_writable_refuses_before_work(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match="under a file"):
        check_writable(tmp_path / "f" / "sub" / "deeper")
    with pytest.raises(InputError, match="not a folder"):
        check_writable(tmp_path / "f")
    with pytest.raises(InputError, match="is a folder"):
        check_writable(tmp_path, kind="file")
    check_writable(tmp_path / "new" / "deeper")  # creatable: fine, and nothing is created
    assert not (tmp_path / "new").exists() and sorted(os.listdir(tmp_path)) == ["f"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders; the /proc rows of "
                    "test_malformed.py cover an unwritable place for root")
def test_read_only_output_folder(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        scene = blender_scene(tmp_path / "s")
        assert main(["inspect", str(scene), "--out", str(ro / "x")]) == 2
        err = capsys.readouterr().err.strip()
        assert "cannot write" in err and str(ro / "x") in err and "\n" not in err
    finally:
        ro.chmod(0o755)


def test_stale_temporaries_are_removed_by_the_next_run(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    write_marker(out, "synth")  # a folder an earlier synth wrote (a folder without the marker is a user's: refused)
    pid = dead_pid()
    stale = [out / f".summary.pid{pid}.abc123.json", out / f".cameras.pid{pid}.x.png"]
    for f in stale:
        f.write_bytes(b"")
    (out / f".viewer.pid{pid}.q1w2").mkdir()
    (out / f".viewer.pid{pid}.q1w2" / "index.html").write_text("half")
    (out / f".scene_00001.tmp{pid}").mkdir()
    live = out / f".summary.pid{os.getpid()}.zz.json"  # a running process's temporary: kept
    live.write_bytes(b"")
    foreign = out / ".keep.pid-not-a-number"  # not our naming: kept
    foreign.write_bytes(b"")
    # synth fills its folder in place (verbs that replace their folder whole drop everything in it anyway)
    assert main(["synth", "--num-scenes", "1", "--views", "2", "--resolution", "16", "--out", str(out)]) == 0
    left = sorted(p.name for p in out.iterdir() if p.name.startswith("."))
    assert left == sorted([live.name, foreign.name, MARKER]), left
    assert len(list(out.glob("scene_*/transforms_train.json"))) == 1


def test_clean_stale_recursive(tmp_path):
    pid = dead_pid()
    (tmp_path / "checkpoints" / "step_0000002").mkdir(parents=True)
    f = tmp_path / "checkpoints" / "step_0000002" / f".model.pid{pid}.a.safetensors"
    f.write_bytes(b"")
    assert clean_stale(tmp_path) == []  # not recursive: untouched
    assert clean_stale(tmp_path, recursive=True) == [f] and not f.exists()


def test_multi_file_output_is_complete_or_absent(tmp_path):
    paths = [tmp_path / "m.ply", tmp_path / "m.obj", tmp_path / "m.glb"]
    with pytest.raises(RuntimeError), atomic_files(paths) as tmps:
        tmps[0].write_text("ply")
        tmps[1].write_text("obj")
        raise RuntimeError("killed while writing the third")
    assert list(tmp_path.iterdir()) == []  # nothing: no partial set, no temporaries
    with atomic_files(paths) as tmps:
        for t, p in zip(tmps, paths):
            t.write_text(p.suffix)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.glb", "m.obj", "m.ply"]
    assert (tmp_path / "m.obj").read_text() == ".obj" and oct((tmp_path / "m.obj").stat().st_mode & 0o777) != "0o600"


def test_mesh_writes_every_format_or_none(tmp_path, capsys):
    """`omnirecon mesh --out a.ply a.obj a.glb` writes the set; a set with one bad suffix writes nothing."""
    scene = blender_scene(tmp_path / "s", mats=ring_gl(6).tolist())
    bad = [str(tmp_path / "b.ply"), str(tmp_path / "b.obj"), str(tmp_path / "b.xyz")]
    assert main(["mesh", "--scene", str(scene), "--model", "floor", "--threads", "1", "--out", *bad]) == 2
    assert not list(tmp_path.glob("b*")) and not list(tmp_path.glob(".b*"))


# ---------------------------------------------------------------------- the command line
def test_verbose_exits_2_with_the_traceback(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "omnirecon.cli", "inspect", str(tmp_path / "nope"), "--verbose"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" in proc.stderr and "InputError" in proc.stderr
    assert proc.stderr.strip().splitlines()[0].startswith("omnirecon: error:")


def test_unknown_flag_is_one_line_in_a_terminal_too():
    """The parse-error box is drawn with Unicode box characters on a terminal, ASCII without one."""
    from omnirecon.cli_errors import parse_error_line

    unicode_box = ("\u256d\u2500 Unrecognized options \u2500\u2500\u2500\u256e\n\u2502 Unrecognized options: --bogus "
                   "\u2502\n\u2502 \u2500\u2500\u2500\u2500 \u2502\n\u2502 For full helptext, run omnirecon --help "
                   "\u2502\n\u2570\u2500\u2500\u2500\u256f\n")
    ascii_box = " Unrecognized options \n ------ \n  Unrecognized options: --bogus \n  ------\n  For full helptext\n"
    for box in (unicode_box, ascii_box):
        line = parse_error_line(box, "inspect")
        assert line == "Unrecognized options: --bogus (fix: see `omnirecon inspect --help` for the flags)", line


# ---------------------------------------------------------------------- --chunk from memory
def test_chunk_default_follows_available_memory():
    from omnirecon.chunk import BYTES_PER_RAY, DEFAULT_MAX, MIN_CHUNK, ceiling, default_chunk

    assert default_chunk(available=64 * 2**30) == DEFAULT_MAX  # plenty: the former default
    assert default_chunk(available=2 * 2**30) == 2048  # 25% of 2 GiB / 140 kB = 3834 -> 2048
    assert default_chunk(available=10**6) == MIN_CHUNK
    for avail in (2**30, 3 * 2**30, 7 * 2**30):
        c = default_chunk(available=avail)
        assert c * BYTES_PER_RAY <= 0.25 * avail or c == MIN_CHUNK
    assert ceiling(total=16 * 2**30) == int(0.25 * 16 * 2**30 / BYTES_PER_RAY)


def test_chunk_above_the_ceiling_gets_a_one_line_note(capsys):
    from omnirecon.chunk import ceiling, pick_chunk

    assert pick_chunk(1024) == 1024 and capsys.readouterr().err == ""
    big = ceiling() + 1
    assert pick_chunk(big) == big  # the user's value is kept
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("omnirecon: note: --chunk") and "25%" in err, err


def test_render_without_chunk_uses_the_memory_default(tmp_path, capsys):
    scene = blender_scene(tmp_path / "s", mats=ring_gl(6).tolist())
    out = tmp_path / "r"
    assert main(["render", "--scene", str(scene), "--model", "floor", "--frames", "1", "--resolution", "8",
                 "--num-views", "2", "--no-video", "--threads", "1", "--device", "cpu", "--out", str(out)]) == 0
    assert len(list((out / "frames").glob("*.png"))) == 1
