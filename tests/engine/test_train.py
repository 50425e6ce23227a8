"""``omnirecon train``: learning, exact resume, checkpoints, 2-process DDP and refusals.

Tiny models (via --model-overrides) on 32x32 procedural scenes of 10 views generated into tmp_path.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import ROOT

from omnirecon.cli import main
from omnirecon.data.synth import SynthOptions, generate_scene
from omnirecon.engine.checkpoint import load_checkpoint
from omnirecon.engine.train import lr_factor
from omnirecon.engine.train_config import parse_overrides

TINY = {
    "gpnr-tiny": ["num_samples=8", "dim=32", "mlp_dim=32", "heads=1", "layers=[1,1,1]", "point_freqs=4"],
    "ibrnet-tiny": ["coarse_samples=8", "fine_samples=4", "channels=[8,8,16]", "feature_dim=8"],
}


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """One procedural object scene (seed 0), 10 views of 32x32."""
    return generate_scene(tmp_path_factory.mktemp("scenes"), 0, SynthOptions(views=10, resolution=32, max_objects=3))


def train_args(out: Path, data: str, model: str = "gpnr-tiny", steps: int = 10, *extra: str) -> list[str]:
    return ["train", "--model", model, "--model-overrides", *TINY[model], "--data", data, "--resolution", "32",
            "--steps", str(steps), "--rays", "64", "--warmup", "2", "--log-every", "1", "--val-every", "0",
            "--ckpt-every", "0", "--out", str(out), "--cache", str(out.parent / "cache"), "--threads", "1",
            "--no-progress", *extra]


def losses(run: Path) -> dict[int, float]:
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    return {r["step"]: r["loss"] for r in rows if "loss" in r}


def weights(folder: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(folder)[0].state_dict()


@pytest.mark.parametrize("model, factor", [("gpnr-tiny", 2.0), ("ibrnet-tiny", 1.8)])
def test_overfits_one_scene(tmp_path, scene, model, factor):
    """50 steps on one scene cut the loss (mean of the first 5 steps vs the last 5) by >= 2x (gpnr), 1.8x (ibrnet).

    Measured on this scene (seed 0): gpnr 2.7x, ibrnet 2.2x. Over seeds 0-7 the 50-step factor spans
    1.2x-3.5x: it is largest where the untrained output (about grey) is far from the scene's colours."""
    run = tmp_path / "run"
    assert main(train_args(run, str(scene), model, 50, "--lr", "3e-3", "--warmup", "5", "--switch-every", "50")) == 0
    loss = losses(run)
    first = sum(loss[s] for s in range(1, 6)) / 5
    last = sum(loss[s] for s in range(46, 51)) / 5
    print(f"{model}: loss {first:.4f} -> {last:.4f} ({first / last:.2f}x)")
    assert first / last >= factor


@pytest.mark.parametrize("model", ["gpnr-tiny", "ibrnet-tiny"])
def test_exact_resume(tmp_path, scene, model):
    """2N steps straight == N steps, stop, --resume, N more: same loss at every step, same weights."""
    n, data = 5, str(scene.parent)  # a folder of scenes
    straight, split = tmp_path / "straight", tmp_path / "split"
    assert main(train_args(straight, data, model, 2 * n, "--ckpt-every", "3")) == 0
    assert main(train_args(split, data, model, 2 * n, "--stop-at", str(n))) == 0
    assert json.loads((split / "summary.json").read_text())["step"] == n
    assert main(train_args(split, data, model, 2 * n, "--resume")) == 0
    a, b = losses(straight), losses(split)
    assert sorted(b) == list(range(1, 2 * n + 1))  # the resumed run appends to metrics.jsonl
    for s in range(n + 1, 2 * n + 1):
        assert a[s] == b[s], (s, a[s], b[s])
    wa, wb = weights(straight / "checkpoints" / "final"), weights(split / "checkpoints" / "final")
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    # checkpoint folder: the last 2 periodic ones + final, latest -> the newest
    ck = straight / "checkpoints"
    assert sorted(p.name for p in ck.iterdir()) == ["final", "latest", "step_0000009", "step_0000010"]
    assert (ck / "latest").resolve().name == "step_0000010"
    meta = json.loads((ck / "final" / "meta.json").read_text())
    assert meta["step"] == 2 * n and meta["preset"] == model and meta["optimizer"] is not None
    assert not list(ck.rglob(".*"))  # no temporary files left
    # a changed setup refuses to resume
    assert main(train_args(split, data, model, 2 * n, "--resume", "--lr", "1e-2")) == 2


def test_validation_picture_and_resume_refusals(tmp_path, scene, capsys):
    run = tmp_path / "run"
    assert main(train_args(run, str(scene), "gpnr-tiny", 4, "--val-every", "2", "--val-scenes", str(scene))) == 0
    assert sorted(p.name for p in (run / "val").iterdir()) == ["step_0000002.png", "step_0000004.png"]
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows if "val_psnr" in r] == [2, 4]
    assert all(k in rows[0] for k in ("step", "loss", "psnr", "lr", "rays_per_s", "time"))
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["resolved"]["num_views"] == 5 and cfg["resolved"]["pool"] == 10
    assert "run folder" in capsys.readouterr().err
    assert main(train_args(run, str(scene), "gpnr-tiny", 4)) == 2  # has checkpoints, no --resume
    assert "--resume" in capsys.readouterr().err
    assert main(train_args(tmp_path / "empty", str(scene), "gpnr-tiny", 4, "--resume")) == 2


def test_sigterm_checkpoints_the_finished_steps_and_resumes_exactly(tmp_path, scene):
    """``kill PID`` (SIGTERM) mid-run: exit 0, a checkpoint at the last finished step s, and ``--resume`` continues
    exactly (steps s+1, s+2 lose what an uninterrupted run loses)."""
    import signal
    import time

    run, straight = tmp_path / "run", tmp_path / "straight"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "omnirecon.cli", *train_args(run, str(scene), "gpnr-tiny", 500)],
                            cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    metrics, deadline = run / "metrics.jsonl", time.monotonic() + 120
    while (not metrics.is_file() or len(metrics.read_text().splitlines()) < 2) and time.monotonic() < deadline:
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err[-2000:]
    assert "SIGTERM received" in err
    s = json.loads((run / "summary.json").read_text())["step"]
    assert 2 <= s < 500 and max(losses(run)) == s
    assert json.loads((run / "checkpoints" / "latest" / "meta.json").read_text())["step"] == s
    for args in (train_args(run, str(scene), "gpnr-tiny", 500, "--resume", "--stop-at", str(s + 2)),
                 train_args(straight, str(scene), "gpnr-tiny", 500, "--stop-at", str(s + 2))):
        # new processes as the interrupted run's: no state a test before this one left in the worker's torch
        done = subprocess.run([sys.executable, "-m", "omnirecon.cli", *args], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
    a, b = losses(straight), losses(run)
    assert [a[k] for k in range(1, s + 3)] == [b[k] for k in range(1, s + 3)]


def test_ddp_two_processes(tmp_path, scene):
    """torchrun, 2 CPU processes (gloo): exits 0 and both ranks end with identical parameters."""
    run = tmp_path / "run"
    args = train_args(run, str(scene), "gpnr-tiny", 4)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                           "-m", "omnirecon.cli", *args], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["world_size"] == 2 and summary["params_in_sync"]
    d0, d1 = summary["param_sha256"]
    assert d0 == d1
    from omnirecon.engine.checkpoint import param_digest

    assert param_digest(load_checkpoint(run / "checkpoints" / "final")[0]) == d0  # rank 0's checkpoint
    assert json.loads((run / "config.json").read_text())["resolved"]["world_size"] == 2


@pytest.mark.parametrize("argv, message", [
    (["--data", "synth:object:seeds=900003"], "reserved for evaluation"),
    (["--data", "synth:object:seeds=901000"], "reserved for evaluation and validation"),
    (["--data", "synth:moon"], "bad procedural source"),
    (["--model", "floor"], "no trainable parameters"),
    (["--model", "gpnr-huge"], "unknown model"),
    (["--model-overrides", "nonsense=1"], "unknown option"),
    (["--model-overrides", "dim=wide"], "wrong type"),
    (["--model-overrides", "ray_param=sphere"], "must be one of"),
    (["--steps", "0"], "--steps"),
    (["--lr", "0"], "--lr"),
    (["--pool", "2"], "--pool"),
    (["--data-weights", "1", "2"], "--data-weights"),
    (["--amp", "bf16", "--device", "cpu"], "needs CUDA"),
    (["--data", "/nonexistent/scene"], "does not exist"),
])
def test_bad_flags_exit_2(tmp_path, argv, message, capsys):
    assert main(["train", "--out", str(tmp_path / "run"), "--cache", str(tmp_path / "c"), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err


def test_refuses_eval_only_scene_folders(tmp_path, scene, capsys):
    fern = tmp_path / "fern"
    fern.symlink_to(scene, target_is_directory=True)
    assert main(train_args(tmp_path / "run", str(fern))) == 2
    assert "reserved for evaluation" in capsys.readouterr().err
    held = generate_scene(tmp_path / "gen", 900_001, SynthOptions(views=2, resolution=8, min_objects=1, max_objects=1))
    assert main(train_args(tmp_path / "run", str(held))) == 2
    assert "seed 900001" in capsys.readouterr().err


def test_time_budget_stops_with_a_checkpoint(tmp_path, scene, capsys):
    run = tmp_path / "run"
    assert main(train_args(run, str(scene), "gpnr-tiny", 100_000, "--time-budget", "1", "--log-every", "100")) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert 1 <= summary["step"] < 100_000 and summary["time"] >= 1
    assert json.loads((run / "checkpoints" / "final" / "meta.json").read_text())["step"] == summary["step"]
    assert "budget reached" in capsys.readouterr().err
    assert main(train_args(run, str(scene), "gpnr-tiny", 100_000, "--time-budget", "1", "--resume")) == 0
    assert "nothing to do" in capsys.readouterr().err


def test_cpu_budget_counts_process_cpu_seconds(tmp_path, scene, capsys):
    run = tmp_path / "run"
    assert main(train_args(run, str(scene), "gpnr-tiny", 100_000, "--cpu-budget", "1.5", "--log-every", "100")) == 0
    meta = json.loads((run / "checkpoints" / "final" / "meta.json").read_text())
    assert 1 <= meta["step"] < 100_000 and meta["extra"]["cpu_s"] >= 1.5
    assert "budget reached" in capsys.readouterr().err


def test_folder_of_scenes_skips_evaluation_scenes(tmp_path, scene, capsys):
    coll = tmp_path / "coll"
    coll.mkdir()
    (coll / "fern").symlink_to(scene, target_is_directory=True)
    (coll / "mine").symlink_to(scene, target_is_directory=True)
    assert main(train_args(tmp_path / "run", str(coll), "gpnr-tiny", 2)) == 0
    assert "skipped" in capsys.readouterr().err
    assert json.loads((tmp_path / "run" / "config.json").read_text())["resolved"]["train_scenes"] == 1


def test_real_scene_is_downscaled_to_the_training_resolution(tmp_path, shared_data):
    lego = shared_data("blender/lego")
    run = tmp_path / "run"
    # --max-views 12 keeps 3 training views (the rest are val/test): K = 2 sources per target at most
    assert main(train_args(run, str(lego), "ibrnet-tiny", 2, "--max-views", "12", "--num-views", "2", "--val-every", "2",
                           "--val-scenes", str(lego))) == 0
    from PIL import Image

    with Image.open(run / "val" / "step_0000002.png") as im:
        assert im.height == 32 + 2  # one 32-pixel row of GT | render | error (+ 2 px separator)


def test_overrides_and_schedule():
    from omnirecon.models.gpnr import GPNRConfig

    o = parse_overrides(['{"dim": 32}', "visual_transformer=false", "layers=1,1,1", "ray_param=lightslab"], GPNRConfig)
    assert o == {"dim": 32, "visual_transformer": False, "layers": (1, 1, 1), "ray_param": "lightslab"}
    assert lr_factor(5, 100, 10, "cosine", 0.1) == 0.5
    assert lr_factor(10, 100, 10, "cosine", 0.1) == 1.0
    assert abs(lr_factor(100, 100, 10, "cosine", 0.1) - 0.1) < 1e-12
    assert abs(lr_factor(55, 100, 10, "linear", 0.0) - 0.5) < 1e-12


def test_validation_scenes_are_neither_training_nor_evaluation_seeds():
    from omnirecon.data.bank import parse_sources
    from omnirecon.splits import EVAL_SEEDS, TRAIN_SEEDS, VAL_SEEDS

    (refs,) = parse_sources(["synth:object:2"], "val", seed=0, synth_scenes=2, cache=Path("unused"), resolution=32,
                            synth_views=8)
    seeds = [r.seed for r in refs]
    assert seeds == list(VAL_SEEDS[:2])
    assert not any(s in EVAL_SEEDS or s in TRAIN_SEEDS for s in seeds)


def test_view_count_range_is_drawn_per_step_and_resumes_exactly(tmp_path, scene):
    """--num-views-range draws K per step within [lo, hi] (both ends occur), seeded by the step, so a run
    stopped and resumed gives the same losses; validation keeps the preset's K."""
    from omnirecon.engine.distributed import DistEnv
    from omnirecon.engine.train import Trainer
    from omnirecon.engine.train_config import TrainConfig

    cfg = TrainConfig(model="gpnr-tiny", data=(str(scene),), resolution=32, steps=4, num_views_range=(2, 6),
                      out=tmp_path / "probe", cache=tmp_path / "cache", progress=False)
    trainer = Trainer(cfg, DistEnv.from_env())
    try:
        drawn = [trainer.views_at(s) for s in range(1, 201)]
        assert drawn == [trainer.views_at(s) for s in range(1, 201)]
        assert {k for k, _ in drawn} == {2, 3, 4, 5, 6} and all(pool == 2 * k for k, pool in drawn)
        assert trainer.K == 5
    finally:
        trainer.close()
    n, extra = 3, ("--num-views-range", "2", "6")
    straight, split = tmp_path / "straight", tmp_path / "split"
    assert main(train_args(straight, str(scene), "gpnr-tiny", 2 * n, *extra)) == 0
    assert main(train_args(split, str(scene), "gpnr-tiny", 2 * n, "--stop-at", str(n), *extra)) == 0
    assert main(train_args(split, str(scene), "gpnr-tiny", 2 * n, "--resume", *extra)) == 0
    a, b = losses(straight), losses(split)
    assert all(a[s] == b[s] for s in range(1, 2 * n + 1)), (a, b)
    assert main(train_args(tmp_path / "bad", str(scene), "gpnr-tiny", 2, "--num-views-range", "6", "2")) == 2


def test_init_warm_starts_from_a_checkpoint_with_a_fresh_schedule(tmp_path, scene, capsys):
    """``--init CKPT``: step 0's weights are the checkpoint's (so the first loss equals the loss the source run
    would see on the same draw), the step count and optimizer start fresh; a wrong preset or config is refused."""
    data = str(scene)
    src = tmp_path / "src"
    assert main(train_args(src, data, "gpnr-tiny", 30, "--lr", "3e-3", "--warmup", "5")) == 0
    ckpt = src / "checkpoints" / "final"
    # zero steps of learning (lr 0 is refused, so compare the weights after a --stop-at 1 with lr ~ 0)
    warm = tmp_path / "warm"
    assert main(train_args(warm, data, "gpnr-tiny", 4, "--init", str(ckpt), "--lr", "1e-12")) == 0
    assert "warm start from" in capsys.readouterr().err
    w0, w1 = weights(ckpt), weights(warm / "checkpoints" / "final")
    assert all(torch.allclose(w0[k], w1[k], atol=1e-6) for k in w0)
    meta = json.loads((warm / "checkpoints" / "final" / "meta.json").read_text())
    assert meta["step"] == 4 and meta["train_config"]["init"] == str(ckpt)
    cold = tmp_path / "cold"
    assert main(train_args(cold, data, "gpnr-tiny", 4, "--lr", "1e-12")) == 0
    assert losses(warm)[1] < losses(cold)[1]  # the warm start has learned something; the cold one has not
    # --resume continues from the run's own checkpoint, --init is ignored then
    assert main(train_args(warm, data, "gpnr-tiny", 5, "--init", str(ckpt), "--lr", "1e-12", "--resume")) == 0
    assert sorted(losses(warm)) == [1, 2, 3, 4, 5]
    # refusals: another preset's checkpoint, a different model config, a folder that is no checkpoint
    assert main(train_args(tmp_path / "r1", data, "ibrnet-tiny", 2, "--init", str(ckpt))) == 2
    assert "gpnr-tiny model, not ibrnet-tiny" in capsys.readouterr().err
    assert main(train_args(tmp_path / "r2", data, "gpnr-tiny", 2, "--init", str(ckpt), "--model-overrides",
                           "dim=16")) == 2
    assert "do not fit" in capsys.readouterr().err
    assert main(train_args(tmp_path / "r3", data, "gpnr-tiny", 2, "--init", str(tmp_path))) == 2
    assert "--init needs a checkpoint folder" in capsys.readouterr().err


def test_mix_resolution_reads_a_share_of_the_scenes_at_a_second_size_and_resumes_exactly(tmp_path, capsys):
    """``--mix-resolution R --mix-share p``: each scene drawn (every ``--switch-every`` steps) is read at ``R`` with
    odds ``p`` (seeded, so the draw repeats and a resumed run gives the same losses); procedural scenes are
    generated at both sizes; the log says each step's size."""
    from omnirecon.engine.distributed import DistEnv
    from omnirecon.engine.train import Trainer
    from omnirecon.engine.train_config import TrainConfig

    cfg = TrainConfig(model="gpnr-tiny", data=("synth:object:1",), synth_scenes=1, resolution=24, mix_resolution=16,
                      mix_share=0.25, switch_every=2, steps=4, out=tmp_path / "probe", cache=tmp_path / "cache",
                      progress=False)
    trainer = Trainer(cfg, DistEnv.from_env())
    try:
        sizes = [trainer.bank_at(s).resolution for s in range(1, 401)]
        assert sizes == [trainer.bank_at(s).resolution for s in range(1, 401)]
        assert all(sizes[i] == sizes[i + 1] for i in range(0, 400, 2))  # one size per scene drawn
        assert 0.15 < sizes.count(16) / 400 < 0.35
    finally:
        trainer.close()
    extra = ("--data", "synth:object:1", "--synth-scenes", "1", "--mix-resolution", "16", "--mix-share", "0.5",
             "--switch-every", "1")
    straight, split = tmp_path / "straight", tmp_path / "split"
    assert main(train_args(straight, "synth:object:1", "gpnr-tiny", 8, *extra[2:])) == 0
    rows = [json.loads(line) for line in (straight / "metrics.jsonl").read_text().splitlines()]
    assert {r["resolution"] for r in rows if "loss" in r} == {16, 32}
    assert {p.name for p in (tmp_path / "cache").iterdir()} >= {"object_16", "object_32"}
    assert main(train_args(split, "synth:object:1", "gpnr-tiny", 8, "--stop-at", "4", *extra[2:])) == 0
    assert main(train_args(split, "synth:object:1", "gpnr-tiny", 8, "--resume", *extra[2:])) == 0
    a, b = losses(straight), losses(split)
    assert all(a[s] == b[s] for s in range(1, 9)), (a, b)
    assert main(train_args(tmp_path / "bad", "synth:object:1", "gpnr-tiny", 2, "--mix-resolution", "4")) == 2
    assert "--mix-resolution" in capsys.readouterr().err
