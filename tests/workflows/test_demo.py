"""``omnirecon demo --quick``: the whole pipeline on the embedded scene, with the shipped checkpoints."""

import json

import pytest
import trimesh
from conftest import ROOT

from omnirecon.cli import main


@pytest.mark.slow
def test_demo_quick_writes_report_with_numbers(tmp_path, capsys):
    shipped = [m for m in ("gpnr-tiny", "ibrnet-tiny") if (ROOT / "checkpoints" / m / "model.safetensors").is_file()]
    if len(shipped) < 2:
        pytest.skip("the shipped gpnr-tiny / ibrnet-tiny checkpoints are not in this clone")
    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", str(out)]) == 0, capsys.readouterr().err
    numbers = json.loads((out / "demo.json").read_text())
    assert {"floor", "gpnr-tiny", "ibrnet-tiny"} <= set(numbers["scores"])
    assert all(10 < s["psnr"] < 60 for s in numbers["scores"].values())  # measured, finite, not trivial
    meshed = "omnirecon-tiny" if (ROOT / "checkpoints" / "omnirecon-tiny" / "model.safetensors").is_file() else "ibrnet-tiny"
    assert set(numbers["mesh"]) == {meshed}  # one all-view mesh: the first shipped of demo.MESH_MODELS
    assert numbers["mesh"][meshed]["faces"] > 0 and numbers["mesh"][meshed]["chamfer"] > 0
    written = trimesh.load(out / f"mesh_{meshed}.ply", process=False, force="mesh")
    assert numbers["mesh"][meshed]["faces"] == len(written.faces)  # the mesh written, not the count before decimation
    page = (out / "index.html").read_text()
    for name in ("cameras.png", "orbit_gpnr-tiny/video", f"mesh_{meshed}.glb", "eval_floor/"):
        assert name in page, name
    for ref in [p.split('"')[0] for p in page.split('src="')[1:]]:
        assert (out / ref).is_file(), ref  # every picture the page shows exists
    printed = capsys.readouterr().out
    assert "report:" in printed
    stages = next(line for line in printed.splitlines() if "seconds per stage:" in line)
    assert all(f"{k} " in stages for k in numbers["seconds"] if k != "total")  # every timed stage printed
    assert set(numbers["cpu_seconds"]) == set(numbers["seconds"]) - {"total"}  # CPU seconds beside wall, per stage
    assert all(v >= 0 for v in numbers["cpu_seconds"].values()) and numbers["threads"] >= 1
    assert "sobel" in numbers["lift"] and "oracle-labels" in numbers["lift"]  # lifting ran (edges and labels)
    if (ROOT / "checkpoints" / "omnirecon-tiny" / "model.safetensors").is_file():
        assert numbers["mesh_path"]["fps"] > 1 and "finetune" in numbers and numbers["mesh"]["omnirecon-tiny"]["faces"] > 0
        lod = numbers["mesh_path"]["lod"]  # the faces drawn, chosen on left-out photos (omnirecon.engine.lod)
        drawn = numbers["mesh_path"]["faces_drawn"]
        assert drawn <= numbers["mesh"]["omnirecon-tiny"]["faces"] and "level of detail: " in printed
        at_budget = [r["faces"] for r in lod["rows"] if r["budget"] == lod["face_budget"] and not r.get("photographed")]
        assert lod["rows"] == [] or (drawn < at_budget[0] if lod["photographed"] else drawn == at_budget[0])
        for name in ("mesh_path/orbit", "finetune/curve.png", "orbit_omnirecon-tiny/video", "overview.png"):
            assert name in page, name


def test_demo_bad_data_exit_2(tmp_path, capsys):
    assert main(["demo", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing" in err[0]
