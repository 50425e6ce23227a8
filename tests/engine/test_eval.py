"""``omnirecon eval``: protocols, end-to-end runs on a tiny procedural scene (floor and a random GPNR
checkpoint), bad input, and the real scenes' protocol choices."""

import json
import math
import time
from pathlib import Path

import pytest
import torch

from omnirecon.data.scene import Scene
from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.engine.checkpoint import save_checkpoint
from omnirecon.engine.evaluate import evaluate
from omnirecon.engine.protocols import PROTOCOLS, targets_and_pool
from omnirecon.engine.scenes import load_at_resolution, prepare_scenes
from omnirecon.metrics import psnr
from omnirecon.models.registry import build_model
from tests.data.test_bad_input import ring_c2w

TINY_GPNR = {"num_samples": 8, "patch_size": 3, "patch_channels": 4, "dim": 16, "mlp_dim": 16, "heads": 1,
             "layers": [1, 1, 1], "ray_freqs": 1, "point_freqs": 1}


@pytest.fixture(scope="module")
def synth_scene(tmp_path_factory) -> Path:
    """A 40 x 40 procedural scene of 16 views: test views 0 and 8, 12 train views in the pool."""
    return generate_scene(tmp_path_factory.mktemp("synth"), 900_123, SynthOptions(resolution=40, views=16))


def fake_scene(n: int, splits: dict | None = None) -> Scene:
    from omnirecon.cameras import Cameras

    cams = Cameras(torch.full((n,), 10.0), torch.full((n,), 10.0), 4.0, 4.0, ring_c2w(n), 8, 8)
    return Scene(torch.zeros(n, 8, 8, 3), cams, torch.ones(n), torch.full((n,), 9.0),
                 torch.tensor([[-1.0] * 3, [1.0] * 3]), splits or {}, rig="object")


def test_protocol_rules():
    t, p = targets_and_pool(PROTOCOLS["dtu"], fake_scene(49))
    assert len(t) == 8 and not {23, 24, 33} & set(t)
    assert t[0] == 0 and t[-1] == 48  # evenly spread over the 46 non-source views
    assert sorted(p + t) == list(range(49)) and {23, 24, 33} <= set(p)
    assert dict(PROTOCOLS["dtu"].fixed_sources)[3] == (23, 24, 33)
    t, p = targets_and_pool(PROTOCOLS["llff"], fake_scene(20))
    assert t == [0, 8, 16] and p == [i for i in range(20) if i % 8]
    blender = fake_scene(30, {"train": list(range(10)), "val": list(range(10, 15)), "test": list(range(15, 30))})
    t, p = targets_and_pool(PROTOCOLS["blender"], blender)
    assert t == list(range(15, 23)) and p == list(range(10))
    t, _ = targets_and_pool(PROTOCOLS["blender"], blender, max_targets=2)
    assert t == [15, 16]
    with pytest.raises(Exception, match="no test split"):
        targets_and_pool(PROTOCOLS["synth"], fake_scene(5))


def test_eval_floor_cli(synth_scene, tmp_path, capsys, run_cli):
    out = tmp_path / "floor"
    code, stdout, err = run_cli(["eval", "--model", "floor", "--scenes", synth_scene, "--num-views", 3, 20, "--out", out])
    assert code == 0, err
    result = json.loads((out / "results.json").read_text())
    md = (out / "results.md").read_text()
    assert md.startswith("# Evaluation: floor") and "Provenance: commit" in md
    assert result["provenance"]["commit"] and result["provenance"]["seed"] == 0
    scene = result["scenes"][0]
    assert scene["protocol"] == "synth" and scene["resolution"] == [40, 40]
    assert scene["skipped"] == {"20": "the source pool has 12 views, fewer than 20"}  # said, not silently dropped
    assert "K=20 skipped" in stdout and "K=20 skipped" in md
    views = scene["settings"]["3"]["views"]
    assert len(views) == 2 and all(len(v["sources"]) == 3 for v in views)
    assert len(list((out / scene["name"] / "k3").glob("*.png"))) == 2
    assert {"psnr", "ssim", "seconds"} <= set(views[0])
    # Sanity floor: well above a constant grey prediction (measured: floor ~22.6 dB, grey ~8.3 dB).
    s = load_at_resolution(synth_scene, 128)
    grey = sum(psnr(torch.full_like(s.images[v["index"]], 0.5), s.images[v["index"]]) for v in views) / len(views)
    floor = result["means"]["synth"]["3"]["psnr"]
    assert floor > grey + 8, (floor, grey)


def test_eval_random_gpnr_checkpoint_cli(synth_scene, tmp_path, capsys, run_cli):
    torch.manual_seed(0)
    ckpt = tmp_path / "ckpt"
    save_checkpoint(ckpt, build_model("gpnr-tiny", TINY_GPNR), "gpnr-tiny", step=7)
    out = tmp_path / "gpnr"
    code, stdout, err = run_cli(["eval", "--ckpt", ckpt, "--scenes", synth_scene, "--num-views", 3, "--out", out,
                         "--max-targets", 1, "--chunk", 512])
    assert code == 0, err
    result = json.loads((out / "results.json").read_text())
    assert result["model"]["preset"] == "gpnr-tiny" and result["model"]["step"] == 7
    assert result["non_protocol"] == {"max_targets": 1}
    mean = result["means"]["synth"]["3"]
    assert {"psnr", "psnr_aux", "ssim", "ssim_aux"} <= set(mean)  # rgb and rgb_aux both scored
    assert "psnr_aux" in (out / "results.md").read_text()
    assert len(list(out.rglob("*.png"))) == 2  # render panel and aux panel
    assert all(math.isfinite(mean[k]) for k in ("psnr", "psnr_aux"))


def test_evaluate_api_is_deterministic_without_output(synth_scene):
    kwargs = dict(num_views=(3,), max_targets=1, progress=False)
    start = time.perf_counter()
    a = evaluate(build_model("floor"), [synth_scene], **kwargs)
    elapsed = time.perf_counter() - start
    b = evaluate(build_model("floor"), [synth_scene], **kwargs)
    assert a["means"]["synth"]["3"]["psnr"] == b["means"]["synth"]["3"]["psnr"]
    # one target view was rendered: its time is part of the call's, and not a rounding zero
    assert 1e-4 < a["seconds_per_view"] <= elapsed


@pytest.mark.parametrize("args, message", [
    (["--ckpt", "{tmp}/nope", "--scenes", "{scene}"], "checkpoint folder not found"),
    (["--ckpt", "{tmp}", "--scenes", "{scene}"], "not a checkpoint folder"),
    (["--model", "floor", "--scenes", "{tmp}/missing_scene"], "path does not exist"),
    (["--model", "floor", "--scenes", "{tmp}"], "no supported scene format"),
    (["--scenes", "{scene}"], "exactly one of --ckpt or --model"),
    (["--model", "floor", "--scenes", "synth:eval:sideways"], "bad scene spec"),
    (["--model", "floor", "--scenes", "{scene}", "--num-views", "0"], "--num-views"),
    (["--model", "floor", "--scenes", "{scene}", "--threads", "0"], "--threads"),
])
def test_eval_bad_input_exit_2(args, message, synth_scene, tmp_path, capsys, run_cli):
    inputs = tmp_path / "in"  # --out beside the inputs: an --out inside an input is refused first
    inputs.mkdir()
    args = [a.format(tmp=inputs, scene=synth_scene) for a in args]
    code, _, err = run_cli(["eval", *args, "--out", tmp_path / "out"])
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("omnirecon: error:") and message in lines[0]


@pytest.mark.parametrize("rel, protocol, size, targets", [
    ("neus_dtu/dtu_scan24", "dtu", [128, 96], [0, 6, 13, 19, 28, 35, 42, 48]),
    ("llff/fern", "llff", [128, 96], [0, 8, 16]),
])
def test_real_scene_protocols(rel, protocol, size, targets, shared_data):
    es = prepare_scenes([shared_data(rel)])[0]
    assert es.protocol.name == protocol and [es.scene.width, es.scene.height] == size
    t, pool = targets_and_pool(es.protocol, es.scene)
    assert t == targets and not set(t) & set(pool)
    assert es.scene.bounds.abs().max() <= 1.0  # normalised as training does


def test_cpu_protocol_set_is_the_full_rules_at_64_px(shared_data):
    from omnirecon.engine.protocols import PROTOCOL_SETS, targets_and_pool
    from omnirecon.engine.scenes import prepare_scenes

    full = prepare_scenes([shared_data("llff/fern")], protocol_set="full")[0]
    cpu = prepare_scenes([shared_data("llff/fern")], protocol_set="cpu")[0]
    assert max(cpu.scene.width, cpu.scene.height) == 64 and max(full.scene.width, full.scene.height) == 128
    t_full, pool_full = targets_and_pool(full.protocol, full.scene)
    t_cpu, pool_cpu = targets_and_pool(cpu.protocol, cpu.scene)
    assert set(t_cpu) <= set(t_full) and len(t_cpu) <= PROTOCOL_SETS["cpu"]["llff"].max_targets
    assert pool_cpu == pool_full  # the same rule picks the same source pool


def test_eval_geometry_scores_a_mesh_and_depth(synth_scene, tmp_path):
    out = tmp_path / "geo"
    result = evaluate(build_model("floor"), [synth_scene], num_views=(3,), out=out, progress=False, geometry=True)
    setting = result["scenes"][0]["settings"]["3"]
    geo = setting["geometry"]
    assert len(geo["views"]) == 3 and not set(geo["views"]) & set(result["scenes"][0]["targets"])
    assert geo["faces"] > 0 and 0 < geo["chamfer"] < geo["threshold"] * 20
    assert math.isclose(geo["chamfer"], (geo["accuracy"] + geo["completeness"]) / 2, rel_tol=1e-6)
    assert 0 <= geo["fscore"] <= 1 and 0 < geo["mask_iou"] <= 1
    assert result["means"]["synth"]["3"]["geometry"]["chamfer"] == geo["chamfer"]
    # The floor renders depth and procedural scenes have GT depth: every target is depth-scored.
    assert all(0 <= v["depth_abs_rel"] < 1 and 0 < v["depth_delta1"] <= 1 for v in setting["views"])
    assert (out / result["scenes"][0]["name"] / "k3" / "mesh.ply").is_file()
    assert "## Geometry" in (out / "results.md").read_text()


def test_eval_geometry_without_a_model_meshes_stereo(synth_scene):
    """A depth source that needs no model: nothing rendered, the same mesh sources as a model's row, a scored
    mesh; without geometry (or with a depth source that needs a model) no model is a one-line error."""
    from omnirecon.errors import InputError
    from omnirecon.mesh.build import MeshOptions

    result = evaluate(None, [synth_scene], num_views=(3,), out=None, progress=False, geometry=True,
                      mesh_options=MeshOptions(depth="stereo"))
    floor = evaluate(build_model("floor"), [synth_scene], num_views=(3,), out=None, progress=False, geometry=True)
    setting = result["scenes"][0]["settings"]["3"]
    geo = setting["geometry"]
    assert setting["views"] == [] and result["mesh_options"]["depth"] == "stereo" and geo["depth_source"] == "stereo"
    assert result["mesh_options"]["surface"] == "auto" and geo["resolved"]["surface"] in ("fusion", "coherent")
    assert geo["resolved"]["depth"] == "stereo" and geo["resolved"]["depth_pass"] == "fine"  # "auto", as it ran
    assert geo["views"] == floor["scenes"][0]["settings"]["3"]["geometry"]["views"]
    assert set(geo["cpu_seconds"]) >= {"depth", "mesh"} and geo["cpu_seconds"]["depth"] >= 0
    if not geo.get("empty"):
        assert geo["faces"] > 0 and 0 <= geo["fscore"] <= 1 and geo["completeness_dropped"] <= 1
    for kwargs in ({}, {"geometry": True}):
        with pytest.raises(InputError, match="without a model"):
            evaluate(None, [synth_scene], num_views=(3,), out=None, progress=False, **kwargs)


def test_cpu256_sets_score_the_rules_and_the_extrapolation_split_at_256_px(shared_data):
    from omnirecon.engine.protocols import CPU256_TARGETS, extrapolation_split, targets_and_pool
    from omnirecon.engine.scenes import prepare_scenes

    for rel in ("llff/fern", "neus_dtu/dtu_scan24"):
        full = prepare_scenes([shared_data(rel)], protocol_set="full")[0]
        big = prepare_scenes([shared_data(rel)], protocol_set="cpu256")[0]
        extra = prepare_scenes([shared_data(rel)], protocol_set="cpu256-extrapolation")[0]
        assert max(big.scene.width, big.scene.height) == 256 and big.protocol.rule == full.protocol.rule
        t_full, _ = targets_and_pool(full.protocol, full.scene)
        t_big, pool_big = targets_and_pool(big.protocol, big.scene)
        assert set(t_big) <= set(t_full) and len(t_big) == CPU256_TARGETS and not set(t_big) & set(pool_big)
        split = extrapolation_split(extra.scene)
        t_x, pool_x = targets_and_pool(extra.protocol, extra.scene)
        assert set(t_x) <= set(split.test) and pool_x == split.train and not extra.protocol.fixed_sources
