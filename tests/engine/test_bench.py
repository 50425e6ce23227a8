import subprocess
import sys

import pytest
from conftest import ROOT

from bench import peer_ibrnet, throughput
from bench.__main__ import main as bench_main
from bench.page import STEPS
from bench.report import common, speed
from bench.report import peer as peer_report


@pytest.fixture(scope="module")
def tiny_page(tmp_path_factory):
    """One ``python -m bench page --tiny`` run (synth, throughput, quality --models floor, geometry --models floor
    stereo, at their --tiny sizes): ``(page, results folder)``, read by the test of each benchmark it ran (one run
    that :func:`test_page_tiny_runs_each_benchmark_and_writes_the_page` checks for each benchmark it ran)."""
    tmp = tmp_path_factory.mktemp("page")
    out, results = tmp / "BENCHMARKS.md", tmp / "results"
    proc = subprocess.run([sys.executable, "-m", "bench", "page", "--tiny", "--out", str(out), "--results", str(results)],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out, results


@pytest.mark.slow
def test_page_tiny_runs_each_benchmark_and_writes_the_page(tiny_page):
    """One test for the one run (a module fixture shared by several tests is built once per pytest-xdist worker that
    runs one of them): the page, then the quality and the geometry rows the page ran."""
    check_page(tiny_page)
    check_quality(tiny_page)
    check_geometry(tiny_page)


def check_page(tiny_page) -> None:
    """The page holds the synth speed table, the geometry section and provenance."""
    out, results = tiny_page
    text = out.read_text()
    assert "2 x 8" in text and "32²" in text and "Provenance: commit" in text
    assert (results / "synth_speed.json").is_file()
    assert "## Geometry from 3 source views" in text and "| floor |" in text  # python -m bench geometry ran and scored


def check_quality(tiny_page) -> None:
    """``bench quality --models floor --tiny`` (as the page runs it): the floor scored on the held-out procedural
    scene with the CPU protocol."""
    import json

    r = json.loads((tiny_page[1] / "quality_floor.json").read_text())
    assert r["protocol_set"] == "cpu" and r["non_protocol"] == {"max_targets": 1}
    psnr = r["means"]["synth"]["3"]["psnr"]
    assert 10 < psnr < 40  # a real measurement on the held-out procedural scene


@pytest.mark.slow
def test_ablation_tiny_trains_and_scores_each_row(tmp_path):
    out = tmp_path / "ablation.json"
    proc = subprocess.run([sys.executable, "-m", "bench", "ablation_gpnr", "--tiny", "--rows", "full",
                           "no ray canonicalization", "--out", str(out)], capture_output=True, text=True, timeout=600,
                          cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    import json

    r = json.loads(out.read_text())
    assert set(r["rows"]) == {"full", "no ray canonicalization"}
    for row in r["rows"].values():
        assert row["steps"] >= 1 and 0 < row["metrics"]["psnr"] < 60 and "psnr_aux" in row["metrics"]


def test_one_entry_point_lists_every_benchmark(capsys):
    """`python -m bench --help` names every benchmark the page runs (and the page); an unknown name exits 2."""
    assert bench_main(["--help"]) == 0
    listed = {line.split()[0] for line in capsys.readouterr().out.splitlines() if line.startswith("  ")}
    aliases = {"synth": "synth_speed", "ablation": "ablation_gpnr"}
    assert {"page", "train_tiny", "profile_models"} | {aliases.get(s, s) for s in STEPS} <= listed
    assert bench_main(["no_such_bench"]) == 2 and "python -m bench --help" in capsys.readouterr().err


def test_page_flags_results_measured_with_another_checkpoint():
    """The page marks a section stale when its stored results name other weights than the shipped ones."""
    now = common.shipped_fingerprint("omnirecon-tiny")
    if now is None:
        pytest.skip("checkpoints/omnirecon-tiny is not in this clone")
    assert len(now["sha256"]) == 16 and now["step"] > 0
    assert common.stale_note("omnirecon-tiny", dict(now), "quality") == []
    old = common.stale_note("omnirecon-tiny", {"step": 5, "sha256": "0" * 16}, "quality")
    assert "step 5" in old[0] and now["sha256"] in old[0] and "python -m bench quality" in old[0]
    assert "unrecorded" in common.stale_note("omnirecon-tiny", None, "lift")[0]


def test_mesh_path_results_are_stale_only_by_what_the_mesh_path_reads(tmp_path):
    """A section that declares the config keys it does not read (the mesh path: the volumetric render options)
    is current when only those changed, for results recorded before the keys existed (their full
    fingerprint) and after (``sha256_ignoring``); new weights or another appearance key still mark it stale."""
    import json
    import shutil

    from omnirecon.engine.checkpoint import fingerprint

    shipped = common.ROOT / "checkpoints" / "omnirecon-tiny"
    if not (shipped / "model.safetensors").is_file():
        pytest.skip("checkpoints/omnirecon-tiny is not in this clone")
    ignore = common.VOLUMETRIC_ONLY
    meta = json.loads((shipped / "meta.json").read_text())
    config = meta["model_config"]
    assert "render_fine_pass" in config  # what made the section look stale
    old = tmp_path / "old"  # the checkpoint as it was before the render options were written into its config
    shutil.copytree(shipped, old)
    (old / "meta.json").write_text(json.dumps({**meta, "model_config": {k: v for k, v in config.items()
                                                                          if k not in ignore}}))
    before = fingerprint(old)
    assert before["sha256"] != common.shipped_fingerprint("omnirecon-tiny")["sha256"]
    assert common.stale_note("omnirecon-tiny", before, "quality")  # the volumetric sections: stale
    assert common.stale_note("omnirecon-tiny", before, "mesh_path", ignore=ignore) == []
    assert common.stale_note("omnirecon-tiny", {**fingerprint(shipped), **common.ignoring(shipped)}, "mesh_path",
                             ignore=ignore) == []
    # a render option flipped after recording: still current for the mesh path, stale for the volumetric path
    flipped = tmp_path / "flipped"
    shutil.copytree(shipped, flipped)
    (flipped / "meta.json").write_text(json.dumps({**meta, "model_config": {**config, "render_fine_pass": True}}))
    rec = {**fingerprint(flipped), **common.ignoring(flipped)}
    assert common.stale_note("omnirecon-tiny", rec, "mesh_path", ignore=ignore) == []
    assert common.stale_note("omnirecon-tiny", rec, "quality")
    # a key the mesh path reads (the appearance MLP) or other weights: stale
    other = tmp_path / "other"
    shutil.copytree(shipped, other)
    (other / "meta.json").write_text(json.dumps({**meta, "model_config": {**config, "blend_hidden": [16, 4]}}))
    note = common.stale_note("omnirecon-tiny", {**fingerprint(other), **common.ignoring(other)}, "mesh_path", ignore=ignore)
    assert note and "python -m bench mesh_path" in note[0]



def test_view_cap_leaves_k3_and_mesh_path_results_current(tmp_path):
    """omnirecon-tiny's ``render_views`` (read only above K = 4): results recorded before it existed stay current
    for sections measured at K = 3 (``ignore=VIEW_CAP``) and for the mesh path recorded with the older, shorter
    list of volumetric keys; the volumetric quality section (K = 10) is stale."""
    import json
    import shutil

    from omnirecon.engine.checkpoint import fingerprint

    shipped = common.ROOT / "checkpoints" / "omnirecon-tiny"
    if not (shipped / "model.safetensors").is_file():
        pytest.skip("checkpoints/omnirecon-tiny is not in this clone")
    meta = json.loads((shipped / "meta.json").read_text())
    assert meta["model_config"]["render_views"] == 4
    old = tmp_path / "old"  # the checkpoint before render_views was written into its config
    shutil.copytree(shipped, old)
    (old / "meta.json").write_text(json.dumps({**meta, "model_config": {
        k: v for k, v in meta["model_config"].items() if k not in common.VIEW_CAP}}))
    before = fingerprint(old)
    assert common.stale_note("omnirecon-tiny", before, "quality")
    assert common.stale_note("omnirecon-tiny", before, "lift", ignore=common.VIEW_CAP) == []
    older_keys = tuple(k for k in common.VOLUMETRIC_ONLY if k not in common.VIEW_CAP)
    rec = {**before, **common.ignoring(old, older_keys)}  # a mesh_path result of the older code
    assert common.stale_note("omnirecon-tiny", rec, "mesh_path", ignore=common.VOLUMETRIC_ONLY) == []
    other = tmp_path / "other"  # a key the mesh path reads changed as well: stale
    shutil.copytree(old, other)
    (other / "meta.json").write_text(json.dumps({**meta, "model_config": {
        **json.loads((old / "meta.json").read_text())["model_config"], "blend_hidden": [16, 4]}}))
    rec = {**fingerprint(other), **common.ignoring(other, older_keys)}
    assert common.stale_note("omnirecon-tiny", rec, "mesh_path", ignore=common.VOLUMETRIC_ONLY)


def test_throughput_compares_reference_twins_and_page_shows_speed(tmp_path):
    """throughput times the reference twins and the defaults in one run; the page renders the Speed table."""
    r = throughput.main(["--quick", "--presets", "floor", "--out", str(tmp_path / "throughput.json")])
    row = r["rows"][0]
    assert row["reference"]["render_rays_per_s"] > 0 and row["speedup_render"] > 0
    text = speed.section(tmp_path)
    assert "## Speed" in text and f"| floor | – | – | –× | {row['reference']['render_rays_per_s']} |" in text


def test_peer_ibrnet_without_checkout_measures_our_side_and_says_so(tmp_path):
    r = peer_ibrnet.main(["--width", "32", "--height", "24", "--train-rays", "16", "--train-steps", "1",
                          "--out", str(tmp_path / "peer_ibrnet.json")])
    assert r["peer_root"] is None and r["ratios"] is None and "no IBRNet checkout" in r["peer_note"]
    ours = r["best"]["ours"]
    assert ours["params"] == 8_957_392 and ours["render_s"] > 0 and ours["train_step_s"] > 0
    text = peer_report.section(tmp_path)
    assert "Reference not measured" in text and "| ours | defaults | 8,957,392 |" in text


def test_peer_ibrnet_rejects_a_folder_that_is_no_checkout(tmp_path):
    from omnirecon.errors import InputError

    with pytest.raises(InputError, match="not an IBRNet checkout"):
        peer_ibrnet.main(["--ibrnet-root", str(tmp_path), "--out", str(tmp_path / "p.json")])


PEER_ROOT = ROOT.parent / "shared" / "peer" / "IBRNet"


@pytest.mark.slow
def test_peer_ibrnet_runs_the_official_code_beside_ours(tmp_path):
    """With the checkout beside the clone: the official code renders and trains (CUDA calls on the CPU), our
    fast paths render bit-identically or within float rounding of our reference twin, and the page shows it."""
    import os

    if not PEER_ROOT.is_dir():
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI must have {PEER_ROOT}")
        pytest.skip(f"{PEER_ROOT} not found: the official IBRNet code sits beside the clone (../shared/peer)")
    pytest.importorskip("configargparse", reason="the reference's option parser: pip install '.[bench]'")
    r = peer_ibrnet.main(["--ibrnet-root", str(PEER_ROOT), "--width", "24", "--height", "18", "--train-rays", "16",
                          "--train-steps", "1", "--reference-too", "--out", str(tmp_path / "peer_ibrnet.json")])
    peer, ours = r["best"]["peer"], r["best"]["ours"]
    assert peer["params"] == ours["params"] == 8_957_392  # the same network on both sides
    assert peer["render_s"] > 0 and peer["train_step_s"] > 0 and r["peer_note"] is None
    assert r["ratios"]["ours"]["render_speedup"] == round(peer["render_cpu_s"] / ours["render_cpu_s"], 2)
    psnr = ours.get("psnr_to_reference_db")
    assert psnr is None or psnr > 60  # None: bit-identical to the reference twin
    text = peer_report.section(tmp_path)
    assert "| peer | official code | 8,957,392 |" in text and "| ours | defaults | 8,957,392 |" in text


def test_train_tiny_stage_spans_split_the_cumulative_cpu_time(tmp_path):
    """The model card's CPU seconds per stage: differences of metrics.jsonl's cumulative cpu_time at the
    stages' boundaries (the last logged row at or before each)."""
    import json

    from bench.train_tiny import stage_spans

    (tmp_path / "stages.json").write_text(json.dumps([{"from_step": 0}, {"from_step": 250}, {"from_step": 300}]))
    rows = [{"step": s, "cpu_time": 2.0 * s} for s in range(10, 301, 10)] + [{"step": 312, "cpu_time": 700.0}]
    assert stage_spans(tmp_path, rows, 312) == [{"from_step": 0, "to_step": 250, "cpu_s": 500.0},
                                                {"from_step": 250, "to_step": 300, "cpu_s": 100.0},
                                                {"from_step": 300, "to_step": 312, "cpu_s": 100.0}]
    (tmp_path / "stages.json").unlink()  # a run from before stages.json: one stage
    assert stage_spans(tmp_path, rows, 312) == [{"from_step": 0, "to_step": 312, "cpu_s": 700.0}]


def test_train_tiny_card_of_a_warm_started_run_adds_the_parent_checkpoint(tmp_path):
    """A run begun with ``--init`` ships a card whose steps and CPU seconds are the parent's plus its own, listing the
    parent's stages first and the run's own (with --init, --lr, --real-weight) after them, its data weights as run."""
    import json

    from bench.train_tiny import ship

    parent = tmp_path / "parent"
    parent.mkdir()
    (parent / "card.json").write_text(json.dumps({
        "steps": 7000, "cpu_seconds": 6700.0, "wall_seconds": 8000.0, "data": {"weights": [2, 2, 2, 1, 1, 1, 1]},
        "stages": ["python bench/train_tiny.py --model ibrnet-tiny --steps 7000"],
        "curve": {"train": [[10, 15.0], [7000, 22.0]], "validation": [[7000, 21.0]]}}))
    run = tmp_path / "run"
    final = run / "checkpoints" / "final"
    final.mkdir(parents=True)
    (final / "model.safetensors").write_bytes(b"weights")
    (final / "meta.json").write_text(json.dumps({"step": 100, "extra": {"cpu_s": 90.0, "elapsed_s": 200.0},
                                                 "model_config": {"num_views": 5}}))
    (run / "stages.json").write_text(json.dumps([{"cpu_budget": 120, "steps": 100, "threads": 1, "from_step": 0,
                                                  "init": str(parent), "lr": "0.0001", "real_weight": "3.0"}]))
    (run / "metrics.jsonl").write_text("".join(json.dumps({"step": s, "loss": 0.01, "psnr": 23.0, "cpu_time": 0.9 * s})
                                               + "\n" for s in range(10, 101, 10)))
    dest = ship("ibrnet-tiny", run, 120, 1, 100, dest=tmp_path / "shipped")
    card = json.loads((dest / "card.json").read_text())
    assert card["steps"] == 7100 and card["cpu_seconds"] == 6790.0 and card["data"]["weights"][-1] == 3.0
    assert card["warm_start"]["steps"] == 7000 and card["stage_spans"] == [{"from_step": 0, "to_step": 100,
                                                                            "cpu_s": 90.0}]
    text = (dest / "MODEL_CARD.md").read_text()
    assert "1. `python -m bench train_tiny --model ibrnet-tiny --steps 7000`" in text
    assert f"--init {parent} --lr 0.0001 --real-weight 3.0` (steps 7000-7100, 90 CPU-s)" in text
    assert (dest / "training_curve.png").stat().st_size > 1000 and (dest / "model.safetensors").read_bytes() == b"weights"


def test_depth3_agreement_counts_only_confident_stereo_pixels_the_model_covers():
    import numpy as np

    from bench.depth3 import agreement

    stereo = np.array([[2.0, 2.0], [2.0, 0.0]])  # one pixel without confident stereo
    pred = np.array([[2.0, 2.08], [3.0, 9.0]])  # exact, 4 % off, 50 % off; the last is not scored
    ok = np.array([[True, True], [True, True]])
    r = agreement(pred, ok, stereo)
    assert r["pixels"] == 3 and r["coverage"] == 1.0
    assert abs(r["abs_rel"] - (0 + 0.04 + 0.5) / 3) < 1e-9
    assert abs(r["within5"] - 2 / 3) < 1e-9 and abs(r["within25"] - 2 / 3) < 1e-9
    ok[1, 0] = False  # the model gives no depth there
    r = agreement(pred, ok, stereo)
    assert r["pixels"] == 2 and abs(r["coverage"] - 2 / 3) < 1e-9 and r["within5"] == 1.0


def check_geometry(tiny_page) -> None:
    """``bench geometry --models floor stereo --tiny`` (as the page runs it): the classical-stereo row: no model, the
    same 3 source views as the model rows, a scored mesh kept on disk, no target render, and the section shows it
    with no PSNR."""
    import json
    from pathlib import Path

    from bench.report import geometry as geometry_report

    results = tiny_page[1]
    stereo = json.loads((results / "geometry_stereo.json").read_text())
    floor = json.loads((results / "geometry_floor.json").read_text())
    s, f = stereo["synth"]["scenes"][0]["settings"]["3"], floor["synth"]["scenes"][0]["settings"]["3"]
    g = s["geometry"]
    assert stereo["synth"]["mesh_options"]["depth"] == "stereo" and g["depth_source"] == "stereo"
    assert f["geometry"]["depth_source"] == "model" and g["views"] == f["geometry"]["views"]  # the same 3 views
    assert s["views"] == [] and "psnr" not in stereo["synth"]["means"]["synth"]["3"]  # nothing rendered
    # stereo matched a real part of the views and the mesh is scored against the exact one
    assert 0.02 < g["valid_depth_fraction"] <= 1 and g["faces"] > 100
    assert 0 < g["chamfer"] < g["threshold"] * 10 and 0 < g["fscore"] <= 1 and 0 < g["mask_iou"] <= 1
    assert stereo["cpu_seconds"]["target_renders"] == 0 < stereo["cpu_seconds"]["depth"]
    assert stereo["cpu_seconds"]["total"] >= sum(v for k, v in stereo["cpu_seconds"].items() if k not in ("total", "other"))
    mesh = Path(next(iter(stereo["meshes"].values())))
    assert mesh.is_file() and results in mesh.parents  # a tiny run never overwrites the real run's meshes
    text = geometry_report.section(results)
    row = next(line for line in text.splitlines() if line.startswith("| stereo |"))
    assert row.rstrip(" |").endswith("–") and "| floor |" in text  # no PSNR without a model to render


def test_finetune_rows_keep_the_provenance_of_their_own_run(tmp_path):
    from bench.finetune_levers import LAST_MERGE, merge
    from bench.report.finetune_levers import commit

    file = tmp_path / "finetune_levers.json"
    merge(file, "fern/a", {"x": 1}, started={"commit": "aaaaaaaaaaaa", "date": "then"})
    result = merge(file, "fern/b", {"x": 2})  # no start given: stamped when merged
    rows = result["rows"]
    assert rows["fern/a"]["provenance"]["commit"] == "aaaaaaaaaaaa"  # a later merge does not restamp it
    assert rows["fern/b"]["provenance"]["commit"] == result["provenance"]["commit"] != "aaaaaaaaaaaa"
    assert result["provenance"]["note"] == LAST_MERGE and "sha256" in rows["fern/a"]["checkpoint"]
    assert commit(rows["fern/a"]) == "`aaaaaaaaaaaa`" and commit({"provenance": {"commit": "b", "recovered": "x"}}) == "~`b`"
    assert commit({}) == "?"
