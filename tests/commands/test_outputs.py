"""Outputs own their folder (omnirecon/outputs.py ``claim``): never inside or around an input, one run per
``--out``, only folders this tool wrote are replaced (and the replacement is said), and an output set is
replaced whole, so an interrupt leaves the old set or the complete new one. The refusals that fit the
malformed-input table (exit 2, one line, nothing written) are rows there; these are the cases that need
a previous output, a second process or an interrupt."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from omnirecon.errors import InputError
from omnirecon.outputs import MARKER, claim, out_lock, read_marker, write_marker
from tests.data.test_bad_input import blender_scene, ring_gl

RENDER = ["--model", "floor", "--resolution", "8", "--num-views", "2", "--no-video", "--device", "cpu",
          "--threads", "1"]
MESH = ["--model", "floor", "--resolution", "16", "--device", "cpu", "--threads", "1", "--max-faces", "0"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return blender_scene(tmp_path_factory.mktemp("outputs") / "scene", mats=ring_gl(6).tolist())


def _files(root: Path) -> dict[str, bytes]:
    """The files under ``root`` but the records of files this tool wrote (``.NAME.omnirecon.json``)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and not p.name.endswith(".omnirecon.json")}


def test_render_replaces_its_frames_whole_and_says_so(scene, tmp_path, run_cli):
    out = tmp_path / "r"
    code, _, err = run_cli(["render", "--scene", scene, "--out", out, "--frames", "3", *RENDER])
    assert code == 0, err
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["0000.png", "0001.png", "0002.png"]
    assert read_marker(out)["command"] == "render"
    code, stdout, err = run_cli(["render", "--scene", scene, "--out", out, "--frames", "1", *RENDER])
    assert code == 0, err
    assert f"replacing {out}: an omnirecon render output" in stdout
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["0000.png"]  # no stale frames
    assert json.loads((out / "cameras.json").read_text())["frames"].__len__() == 1
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "temporaries or lock left beside --out"


def test_render_refuses_a_folder_of_another_command(scene, tmp_path, run_cli):
    out = tmp_path / "scene_out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    (out / MARKER).write_text(json.dumps({"tool": "omnirecon", "command": "process", "written": "earlier"}))
    before = _files(out)
    code, _, err = run_cli(["render", "--scene", scene, "--out", out, *RENDER])
    assert code == 2 and "holds an omnirecon process output" in err and "(fix: " in err, err
    assert _files(out) == before


def test_second_run_on_the_same_out_is_refused_while_the_first_holds_it(scene, tmp_path, run_cli):
    out = tmp_path / "r"
    with out_lock(out, "render"):  # what a first, still running `omnirecon render --out r` holds
        code, _, err = run_cli(["render", "--scene", scene, "--out", out, *RENDER])
        assert code == 2, err
        assert f"another omnirecon run is writing --out (pid {os.getpid()}, omnirecon render)" in err
        assert len(err.strip().splitlines()) == 1
        assert not out.exists()
        code, _, err = run_cli(["mesh", "--scene", scene, "--out", tmp_path / "r", *MESH])  # same path, any verb
        assert code == 2 and "another omnirecon run" in err, err
    code, _, err = run_cli(["render", "--scene", scene, "--out", out, *RENDER])  # released: runs
    assert code == 0, err
    assert not (tmp_path / ".r.lock").exists()


def test_overwrite_replaces_only_marked_folders(tmp_path):
    said = []
    foreign = tmp_path / "photos_and_more"
    foreign.mkdir()
    (foreign / "IMG_0001.JPG").write_bytes(b"a photo")
    with pytest.raises(InputError, match="did not write"):
        with claim(foreign, "process", mode="replace", overwrite=True, say=said.append):
            pass
    assert (foreign / "IMG_0001.JPG").read_bytes() == b"a photo"
    with pytest.raises(InputError, match="already exists"):
        with claim(foreign, "process", mode="replace", overwrite=False):
            pass
    ours = tmp_path / "scene"
    with claim(ours, "process", mode="replace", overwrite=False) as c:
        (c.work / "old.txt").write_text("old")
    with claim(ours, "reconstruct", mode="replace", overwrite=True, say=said.append) as c:
        assert c.work != ours and (ours / "old.txt").is_file()  # the old folder stands until the new is done
        (c.work / "new.txt").write_text("new")
    assert said == [f"replacing {ours}: {c.replaced} (the new one takes its place when complete)"]
    assert "an omnirecon process output written" in said[0]
    assert sorted(p.name for p in ours.iterdir()) == [MARKER, "new.txt"]
    assert read_marker(ours)["command"] == "reconstruct"


@pytest.mark.parametrize("interrupt", [KeyboardInterrupt, RuntimeError])
def test_interrupted_replacement_keeps_the_old_folder(tmp_path, interrupt):
    out = tmp_path / "r"
    with claim(out, "render", mode="replace") as c:
        (c.work / "frame.png").write_text("old")
    with pytest.raises(interrupt):
        with claim(out, "render", mode="replace") as c:
            (c.work / "frame.png").write_text("half")
            raise interrupt()
    assert (out / "frame.png").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"]


def test_a_kill_between_the_two_renames_is_undone(tmp_path):
    """Where the kernel cannot swap two folders in one step, swap_in renames twice; a run killed between
    them leaves ``.NAME.oldPID`` and no NAME: the next run on that --out puts the old folder back."""
    old = tmp_path / ".r.old999999999"
    old.mkdir()
    (old / "frame.png").write_text("old")
    (old / MARKER).write_text(json.dumps({"tool": "omnirecon", "command": "render"}))  # a swapped-out output
    with claim(tmp_path / "r", "render", mode="fill"):
        assert (tmp_path / "r" / "frame.png").read_text() == "old"


def test_inputs_are_never_inside_or_around_out(tmp_path):
    photos = tmp_path / "capture" / "photos"
    photos.mkdir(parents=True)
    (tmp_path / "capture" / "notes.txt").write_text("keep")
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "capture")
    for out, what in ((tmp_path / "capture", "holds the input"), (photos, "inside the input"),
                      (photos / "sub", "inside the input"), (link, "holds the input"), (link / "photos", "inside")):
        with pytest.raises(InputError, match=what):
            with claim(out, "process", inputs=(photos,), mode="replace", overwrite=True):
                pass
    assert sorted(p.name for p in (tmp_path / "capture").iterdir()) == ["notes.txt", "photos"]


def test_mesh_set_is_replaced_whole(scene, tmp_path, run_cli, monkeypatch):
    out = tmp_path / "m.ply"
    code, _, err = run_cli(["mesh", "--scene", scene, "--out", out, *MESH])
    assert code == 0, err
    first = _files(tmp_path)
    assert {"m.ply", "m_metrics.json", "m_preview.png"} <= set(first)
    # Ctrl-C while the new metrics are computed (the last stage): the previous set stays as it was.
    from omnirecon.mesh import geometry

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(geometry, "score_mesh", interrupted)
    code, _, err = run_cli(["mesh", "--scene", scene, "--out", out, "--shifts", "0.05", "0", *MESH])
    assert code == 130 and "interrupted" in err, err
    assert _files(tmp_path) == first
    monkeypatch.undo()
    # A run without metrics or preview: the previous run's metrics and preview go with its mesh.
    code, _, err = run_cli(["mesh", "--scene", scene, "--out", out, "--no-metrics", "--no-preview", *MESH])
    assert code == 0, err
    assert sorted(_files(tmp_path)) == ["m.ply"]


@pytest.mark.parametrize("verb", ["process", "reconstruct", "train", "export", "finetune", "synth", "eval", "inspect",
                                  "lift", "demo"])
def test_every_writing_verb_takes_the_lock(verb, scene, tmp_path, run_cli):
    """The issue's "two runs to one --out" for every writing verb: while a run holds --out, another is refused
    with one line before it does any work (render and mesh: above)."""
    pytest.importorskip("pycolmap") if verb == "process" else None
    out = tmp_path / "o"
    ck = Path(__file__).resolve().parents[2] / "checkpoints" / "omnirecon-tiny"
    args = {"process": ["process", scene / "train"], "reconstruct": ["reconstruct", scene],
            "train": ["train", "--data", scene, "--model", "gpnr-tiny"], "export": ["export", "--scene", scene,
            "--ckpt", ck], "finetune": ["finetune", "--scene", scene, "--ckpt", ck], "synth": ["synth"],
            "eval": ["eval", "--model", "floor", "--scenes", scene], "inspect": ["inspect", scene],
            "lift": ["lift", "--ckpt", ck, "--scene", scene], "demo": ["demo"]}[verb]
    with out_lock(out, "process"):
        code, _, err = run_cli([*args, "--out", out])
    assert code == 2 and "another omnirecon run is writing --out" in err and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_records_name_final_paths_not_the_temporary_folder(tmp_path):
    """What a verb records while it builds in the temporary folder holds for --out after the swap."""
    out = tmp_path / "rec"
    with claim(out, "reconstruct", mode="replace", overwrite=False) as c:
        (c.work / "export").mkdir()
        (c.work / "export" / "export.json").write_text(json.dumps(
            {"files": [str(c.work / "export" / "mesh.glb")], "out": str(c.work.absolute()), "input": str(tmp_path)}))
    assert json.loads((out / "export" / "export.json").read_text()) == {
        "files": ["export/mesh.glb"], "out": ".", "input": str(tmp_path)}


def test_two_rename_fallback_replaces_too(tmp_path, monkeypatch):
    """Kernels or file systems without RENAME_EXCHANGE: the swap is two renames, same result."""
    from omnirecon import outputs

    out = tmp_path / "r"
    with claim(out, "render", mode="replace") as c:
        (c.work / "a.txt").write_text("old")
    monkeypatch.setattr(outputs, "_exchange", lambda a, b: False)
    with claim(out, "render", mode="replace", say=lambda s: None) as c:
        (c.work / "b.txt").write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"]
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "b.txt"]


def test_names_that_are_not_paths_are_not_inputs(tmp_path, monkeypatch):
    """`lift --out .` with the default scene synth:eval: the name is not a folder of the working directory."""
    monkeypatch.chdir(tmp_path)
    with claim(Path("."), "lift", inputs=("synth:eval", None)) as c:
        assert c.work == Path(".")


def test_export_replaces_its_set_whole(scene, tmp_path, run_cli):
    """A second export into the same --out (here without the viewer) leaves no member of the first behind,
    and its record names the final folder."""
    ck = Path(__file__).resolve().parents[2] / "checkpoints" / "omnirecon-tiny"
    code, _, err = run_cli(["mesh", "--scene", scene, "--out", tmp_path / "m.ply", *MESH])
    assert code == 0, err
    out = tmp_path / "e"
    args = ["export", "--scene", scene, "--ckpt", ck, "--mesh", tmp_path / "m.ply", "--no-viewer", "--threads", "1",
            "--device", "cpu", "--out", out]
    code, _, err = run_cli(args)
    assert code == 0, err
    (out / "viewer").mkdir()  # what an earlier export with the viewer left
    (out / "viewer" / "bundle.json").write_text("{}")
    write_marker(out, "export")  # whose marker lists it
    code, stdout, err = run_cli(args)
    assert code == 0 and f"replacing {out}: an omnirecon export output" in stdout, err
    assert f"wrote {out / 'mesh.glb'}" in stdout
    assert not (out / "viewer").exists()
    assert ".tmp" not in (out / "export.json").read_text()


@pytest.mark.parametrize("name", ["m.ply", "m_preview.png", "m_metrics.json"])
def test_mesh_never_replaces_a_users_file(scene, tmp_path, run_cli, name):
    """A file of the set that the user wrote is refused before any work (one line naming it and --overwrite)."""
    (tmp_path / name).write_text("mine")
    code, _, err = run_cli(["mesh", "--scene", scene, "--out", tmp_path / "m.ply", *MESH])
    assert code == 2 and str(tmp_path / name) in err and "--overwrite" in err, err
    assert len(err.strip().splitlines()) == 1, err
    assert _files(tmp_path) == {name: b"mine"}


def test_mesh_replaces_its_own_files_and_a_users_only_with_overwrite(scene, tmp_path, run_cli):
    out = tmp_path / "m.ply"
    (tmp_path / "m_preview.png").write_text("mine")
    code, _, err = run_cli(["mesh", "--scene", scene, "--out", out, "--overwrite", *MESH])
    assert code == 0, err
    assert (tmp_path / "m_preview.png").read_bytes() != b"mine"
    code, _, err = run_cli(["mesh", "--scene", scene, "--out", out, *MESH])  # its own files: replaced
    assert code == 0, err
    # The user puts their own picture in place of the preview; a run without --preview never deletes it.
    (tmp_path / "m_preview.png").write_text("mine again")
    code, _, err = run_cli(["mesh", "--scene", scene, "--out", out, "--no-preview", *MESH])
    assert code == 0, err
    assert (tmp_path / "m_preview.png").read_text() == "mine again"


@pytest.mark.parametrize("held, outs", [(["m.ply"], ["other.ply", "m.ply"]), (["m.ply"], ["m.obj"])])
def test_two_mesh_runs_sharing_a_file_cannot_both_run(scene, tmp_path, run_cli, held, outs):
    """A run holding m.ply's set (m.ply, m_preview.png, m_metrics.json) refuses a second whose set shares a file."""
    from omnirecon.workflows.mesh import MeshConfig, set_files

    first = MeshConfig(scene=scene, out=tuple(tmp_path / h for h in held))
    with claim(first.out[0], "mesh", mode="file", files=set_files(first)):
        code, _, err = run_cli(["mesh", "--scene", scene, "--out", *[tmp_path / o for o in outs], *MESH])
    assert code == 2 and "another omnirecon run is writing --out" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_bench_never_replaces_a_users_file(tmp_path, run_cli):
    (tmp_path / "b.json").write_text("mine")
    code, _, err = run_cli(["bench", "--quick", "--out", tmp_path / "b.json"])
    assert code == 2 and str(tmp_path / "b.json") in err and "--overwrite" in err, err
    assert _files(tmp_path) == {"b.json": b"mine"}


def test_render_never_deletes_a_file_the_user_added(scene, tmp_path, run_cli):
    out = tmp_path / "r"
    code, _, err = run_cli(["render", "--scene", scene, "--out", out, "--frames", "1", *RENDER])
    assert code == 0, err
    (out / "frames" / "notes.txt").write_text("mine")
    before = _files(out)
    code, _, err = run_cli(["render", "--scene", scene, "--out", out, "--frames", "1", *RENDER])
    assert code == 2 and str(out / "frames" / "notes.txt") in err and "never deleted" in err, err
    assert _files(out) == before


def test_train_never_fills_a_users_folder(scene, tmp_path, run_cli):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "config.json").write_text("mine")
    (out / "metrics.jsonl").write_text("mine")
    code, _, err = run_cli(["train", "--data", scene, "--model", "gpnr-tiny", "--steps", "1", "--out", out])
    assert code == 2 and "did not write" in err and str(out) in err, err
    assert _files(out) == {"config.json": b"mine", "metrics.jsonl": b"mine"}
