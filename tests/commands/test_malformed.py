"""Every command against a table of malformed inputs: exit 2, one line on stderr (``omnirecon: error: ...``
naming the file and with a fix clause), no traceback, nothing written (neither the row's ``--out`` nor any
other file under the fixtures or the working folder).

A new command joins by adding rows to ``ROWS``: ``(command-line args, text the message must contain)``;
``{name}`` in either is replaced by the fixture path of that name (see :func:`fixtures`), ``{out}`` by a
fresh path that must not exist afterwards. ``None`` as expected text: a message without a file (a bad
flag), which must still carry a fix clause. The rows run in-process through ``omnirecon.cli.main``.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from omnirecon.cli import main
from tests.data.test_bad_input import blender_scene, colmap_scene, llff_scene, ring_gl, tiny_image

TINY_GPNR = {"num_samples": 8, "dim": 32, "mlp_dim": 32, "heads": 1, "layers": [1, 1, 1], "point_freqs": 4}
RENDER = ["--frames", "1", "--resolution", "8", "--no-video", "--device", "cpu", "--threads", "1"]
TRAIN = ["--model", "gpnr-tiny", "--model-overrides", "num_samples=8", "dim=32", "mlp_dim=32", "heads=1",
         "layers=[1,1,1]", "point_freqs=4", "--resolution", "8", "--steps", "2", "--rays", "16", "--val-every", "0",
         "--threads", "1", "--no-progress", "--cache", "{root}/cache"]

ROWS: list[tuple[list[str], str | None]] = [
    # ---- scenes (inspect reads every format)
    (["inspect", "{root}/nope", "--out", "{out}"], "{root}/nope"),
    (["inspect", "{empty}", "--out", "{out}"], "{empty}"),
    (["inspect", "{a_file}", "--out", "{out}"], "{a_file}"),
    (["inspect", "{missing_image}", "--out", "{out}"], "{missing_image}/train/r_1.png"),
    (["inspect", "{corrupt_image}", "--out", "{out}"], "{corrupt_image}/train/r_2.png"),
    (["inspect", "{bad_json}", "--out", "{out}"], "{bad_json}/transforms_train.json"),
    (["inspect", "{matrix_3x3}", "--out", "{out}"], "{matrix_3x3}/transforms_train.json"),
    (["inspect", "{nan_pose}", "--out", "{out}"], "{nan_pose}/transforms_train.json"),
    (["inspect", "{outside_path}", "--out", "{out}"], "{outside_path}/transforms_train.json"),
    (["inspect", "{absolute_path}", "--out", "{out}"], "{absolute_path}/transforms_train.json"),
    (["inspect", "{no_frames}", "--out", "{out}"], "{no_frames}/transforms_train.json"),
    (["inspect", "{llff_cols}", "--out", "{out}"], "{llff_cols}/poses_bounds.npy"),
    (["inspect", "{llff_bounds}", "--out", "{out}"], "{llff_bounds}/poses_bounds.npy"),
    (["inspect", "{llff_rows}", "--out", "{out}"], "{llff_rows}/images"),
    (["inspect", "{llff_nan}", "--out", "{out}"], "{llff_nan}/poses_bounds.npy"),
    (["inspect", "{neus_keys}", "--out", "{out}"], "{neus_keys}/cameras_sphere.npz"),
    (["inspect", "{neus_singular}", "--out", "{out}"], "{neus_singular}/cameras_sphere.npz"),
    (["inspect", "{mvsnet_cam}", "--out", "{out}"], "{mvsnet_cam}/cams/00000001_cam.txt"),
    (["inspect", "{colmap_trunc}", "--out", "{out}"], "{colmap_trunc}/sparse/0/images.bin"),
    (["inspect", "{colmap_outside}", "--out", "{out}"], "{colmap_outside}/sparse/0/images.txt"),
    (["inspect", "{blender}", "--format", "llff", "--out", "{out}"], "{blender}"),
    (["inspect", "{blender}", "--format", "dtu_neus", "--out", "{out}"], "{blender}"),
    (["inspect", "{llff}", "--format", "blender", "--out", "{out}"], "{llff}"),
    (["inspect", "{blender}", "--max-views", "0", "--out", "{out}"], None),
    (["inspect", "{blender}", "--downscale", "0", "--out", "{out}"], None),
    (["inspect", "{blender}", "--out", "{a_file}/sub"], "{a_file}"),
    (["inspect", "{blender}", "--out", "/proc/omnirecon-no/x"], "/proc/omnirecon-no/x"),
    # ---- checkpoints (render loads one the way every command does)
    (["render", "--scene", "{blender}", "--ckpt", "{ck_no_config}", "--out", "{out}", *RENDER],
     "{ck_no_config}/meta.json"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck_five}", "--out", "{out}", *RENDER], "{ck_five}/meta.json"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck_preset}", "--out", "{out}", *RENDER], "{ck_preset}/meta.json"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck_option}", "--out", "{out}", *RENDER], "{ck_option}/meta.json"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck_meta_list}", "--out", "{out}", *RENDER],
     "{ck_meta_list}/meta.json"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck_meta_bad}", "--out", "{out}", *RENDER],
     "{ck_meta_bad}/meta.json"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck_trunc}", "--out", "{out}", *RENDER],
     "{ck_trunc}/model.safetensors"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck_garbage}", "--out", "{out}", *RENDER],
     "{ck_garbage}/model.safetensors"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck_missing}", "--out", "{out}", *RENDER],
     "{ck_missing}/model.safetensors"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck_nan}", "--out", "{out}", *RENDER], "{ck_nan}/model.safetensors"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck_inf}", "--out", "{out}", *RENDER], "{ck_inf}/model.safetensors"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck_shape}", "--out", "{out}", *RENDER],
     "{ck_shape}/meta.json"),
    (["render", "--scene", "{blender}", "--ckpt", "{empty}", "--out", "{out}", *RENDER], "{empty}"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck}", "--out", "{a_file}/x", *RENDER], "{a_file}"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck}", "--out", "{out}", "--frames", "0", "--no-video"], None),
    (["render", "--scene", "{blender}", "--ckpt", "{ck}", "--out", "{out}", *RENDER, "--chunk", "0"], None),
    (["render", "--scene", "{blender}", "--ckpt", "{ck}", "--out", "{out}", *RENDER, "--resolution", "0"], None),
    (["render", "--scene", "{blender}", "--ckpt", "{ck}", "--out", "{out}", *RENDER, "--path", "interp",
      "--keyframes", "0", "9"], "{blender}"),
    (["render", "--scene", "{missing_image}", "--ckpt", "{ck}", "--out", "{out}", *RENDER],
     "{missing_image}/train/r_1.png"),
    # ---- eval
    (["eval", "--ckpt", "{ck_five}", "--scenes", "{with_test}", "--out", "{out}", "--device", "cpu"], "{ck_five}/meta.json"),
    (["eval", "--ckpt", "{ck_nan}", "--scenes", "{with_test}", "--out", "{out}", "--device", "cpu"],
     "{ck_nan}/model.safetensors"),
    (["eval", "--ckpt", "{ck}", "--scenes", "{with_test}", "--out", "{out}", "--device", "cpu", "--num-views", "50"],
     "--num-views 50"),
    (["eval", "--ckpt", "{ck}", "--scenes", "{with_test}", "--out", "{out}", "--device", "cpu", "--num-views", "0"], None),
    (["eval", "--ckpt", "{ck}", "--scenes", "{with_test}", "--out", "{out}", "--device", "cpu", "--chunk", "0"], None),
    (["eval", "--ckpt", "{ck}", "--scenes", "{root}/nope", "--out", "{out}", "--device", "cpu"], "{root}/nope"),
    (["eval", "--ckpt", "{ck}", "--scenes", "{with_test}", "--out", "{a_file}", "--device", "cpu"], "{a_file}"),
    # ---- mesh
    (["mesh", "--scene", "{blender}", "--model", "floor", "--resolution", "0", "--out", "{out}.ply"], None),
    (["mesh", "--scene", "{blender}", "--ckpt", "{ck_no_config}", "--out", "{out}.ply"], "{ck_no_config}/meta.json"),
    (["mesh", "--scene", "{blender}", "--ckpt", "{ck_trunc}", "--out", "{out}.ply"], "{ck_trunc}/model.safetensors"),
    (["mesh", "--scene", "{blender}", "--model", "floor", "--out", "{out}.xyz"], "{out}.xyz"),
    (["mesh", "--scene", "{blender}", "--model", "floor", "--out", "{a_file}/m.ply"], "{a_file}"),
    (["mesh", "--scene", "{blender}", "--model", "floor", "--num-views", "50", "--out", "{out}.ply"], "{blender}"),
    (["mesh", "--scene", "{blender}", "--model", "floor", "--views", "0", "9", "--out", "{out}.ply"], "{blender}"),
    (["mesh", "--scene", "{outside_path}", "--model", "floor", "--out", "{out}.ply"],
     "{outside_path}/transforms_train.json"),
    # ---- export
    (["export", "--scene", "{blender}", "--ckpt", "{ck}", "--resolution", "0", "--out", "{out}"], None),
    (["export", "--scene", "{blender}", "--ckpt", "{ck_five}", "--out", "{out}"], "{ck_five}/meta.json"),
    (["export", "--scene", "{blender}", "--ckpt", "{ck}", "--mesh", "{root}/nope.ply", "--out", "{out}"],
     "{root}/nope.ply"),
    (["export", "--scene", "{blender}", "--ckpt", "{ck}", "--out", "{a_file}/x"], "{a_file}"),
    # ---- finetune
    (["finetune", "--scene", "{blender}", "--ckpt", "{ck}", "--resolution", "0", "--out", "{out}"], None),
    (["finetune", "--scene", "{blender}", "--ckpt", "{ck_nan}", "--out", "{out}"], "{ck_nan}/model.safetensors"),
    (["finetune", "--scene", "{blender}", "--ckpt", "{ck}", "--out", "{a_file}/x"], "{a_file}"),
    # ---- lift, edit, pet
    (["lift", "--ckpt", "{ck_no_config}", "--scene", "{blender}", "--out", "{out}", "--device", "cpu"],
     "{ck_no_config}/meta.json"),
    (["lift", "--ckpt", "{ck}", "--scene", "{blender}", "--out", "{out}", "--num-views", "0"], None),
    (["lift", "--ckpt", "{ck}", "--scene", "{blender}", "--out", "{out}", "--noise", "2"], None),
    (["lift", "--ckpt", "{ck}", "--scene", "{blender}", "--out", "{a_file}/x"], "{a_file}"),
    (["edit", "--ckpt", "{ck_missing}", "--scene", "{blender}", "--label", "1", "--out", "{out}"],
     "{ck_missing}/model.safetensors"),
    (["edit", "--ckpt", "{ck}", "--scene", "{blender}", "--out", "{out}"], None),
    (["pet", "--ckpt", "{ck_garbage}", "--scene", "{blender}", "--out", "{out}"], "{ck_garbage}/model.safetensors"),
    (["pet", "--ckpt", "{ck}", "--scene", "{blender}", "--out", "{out}", "--labelled", "1"], None),
    # ---- train
    (["train", "--data", "{small}", "--num-views", "50", "--out", "{out}", *TRAIN], "{small}"),
    (["train", "--data", "{missing_image}", "--out", "{out}", *TRAIN], "{missing_image}/train/r_1.png"),
    (["train", "--data", "{outside_path}", "--out", "{out}", *TRAIN], "{outside_path}/transforms_train.json"),
    (["train", "--data", "{small}", "--out", "{out}", "--resume", *TRAIN], "{out}"),
    (["train", "--data", "{small}", "--out", "{a_file}", *TRAIN], "{a_file}"),
    (["train", "--data", "{small}", "--out", "{a_file}/run", *TRAIN], "{a_file}"),
    (["train", "--data", "{small}", "--out", "{out}", *TRAIN, "--steps", "0"], None),
    (["train", "--data", "{small}", "--out", "{out}", *TRAIN, "--keep", "0"], None),
    (["train", "--data", "{small}", "--out", "{run_broken}", "--resume", *TRAIN],
     "{run_broken}/checkpoints/latest"),
    # ---- synth, view, bench, demo
    (["synth", "--num-scenes", "0", "--out", "{out}"], None),
    (["synth", "--seed", "-1", "--out", "{out}"], None),
    (["synth", "--out", "{a_file}"], "{a_file}"),
    (["synth", "--out", "{a_file}/sub"], "{a_file}"),
    (["process", "{root}/nope", "--out", "{out}"], "{root}/nope"),
    (["process", "{empty}", "--out", "{out}"], "{empty}"),
    (["process", "{a_file}", "--out", "{out}"], "{a_file}"),
    (["process", "{blender}/train", "--out", "{blender}/train/sub"], "{blender}/train/sub"),
    (["reconstruct", "{root}/nope", "--out", "{out}"], "{root}/nope"),
    (["reconstruct", "{blender}", "--ckpt", "{root}/nope", "--out", "{out}"], "{root}/nope"),
    (["reconstruct", "{blender}", "--frames", "1", "--out", "{out}"], None),
    (["reconstruct", "{blender}", "--out", "{a_file}/sub"], "{a_file}"),
    (["view", "{root}/nope", "--no-browser"], "{root}/nope"),
    (["view", "{empty}", "--no-browser"], "{empty}"),
    (["bench", "--ckpt", "{ck}", "--resolution", "1", "--out", "{out}.json"], None),
    (["bench", "--ckpt", "{ck}", "--out", "{a_file}/r.json"], "{a_file}"),
    (["demo", "--out", "{a_file}/demo"], "{a_file}"),
    # ---- the command line itself
    (["inspect", "{blender}", "--bogus", "1"], "--bogus"),
    (["frobnicate"], "frobnicate"),
    (["render", "--scene", "{blender}", "--frames", "abc"], "--frames"),
    (["render"], "--scene"),
]

# ---- outputs own their folder (omnirecon/outputs.py claim): an --out inside or around an input, or a folder this
# tool did not write, is refused before any work, whatever --overwrite says (tests/commands/test_outputs.py has
# the cases that need a previous output, a second run or an interrupt).
ROWS += [
    (["process", "{blender}/train", "--out", "{blender}", "--overwrite"], "{blender}"),  # --out holds the photos
    (["process", "{blender}/train", "--out", "{blender}/train", "--overwrite"], "{blender}/train"),
    (["process", "{blender}/train", "--out", "{llff}", "--overwrite"], "{llff}"),  # not ours: never replaced
    (["process", "{blender}/train", "--out", "{llff}"], "{llff}"),
    (["reconstruct", "{blender}", "--out", "{root}", "--overwrite"], "{root}"),  # holds the input
    (["reconstruct", "{blender}", "--out", "{blender}/rec", "--overwrite"], "{blender}/rec"),
    (["reconstruct", "{blender}", "--out", "{llff}", "--overwrite"], "{llff}"),
    (["reconstruct", "{blender}", "--ckpt", "{ck_omni}", "--out", "{ck_omni}/..", "--overwrite"], "{ck_omni}/.."),
    (["render", "--scene", "{blender}", "--ckpt", "{ck}", "--out", "{llff}", *RENDER], "{llff}"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck}", "--out", "{blender}/render", *RENDER], "{blender}/render"),
    (["render", "--scene", "{blender}", "--ckpt", "{ck}", "--out", "{ck}/render", *RENDER], "{ck}/render"),
    (["mesh", "--scene", "{blender}", "--model", "floor", "--out", "{blender}/m.ply"], "{blender}/m.ply"),
    (["mesh", "--scene", "{blender}", "--model", "floor", "--out", "{out}.ply", "{blender}/m.glb"], "{blender}/m.glb"),
    (["export", "--scene", "{blender}", "--ckpt", "{ck_omni}", "--out", "{blender}/x"], "{blender}/x"),
    (["finetune", "--scene", "{blender}", "--ckpt", "{ck_omni}", "--out", "{root}"], "{root}"),
    (["eval", "--ckpt", "{ck}", "--scenes", "{with_test}", "--out", "{with_test}/ev", "--device", "cpu"],
     "{with_test}/ev"),
    (["train", "--data", "{small}", "--out", "{small}/run", *TRAIN], "{small}/run"),
    (["inspect", "{blender}", "--out", "{blender}"], "{blender}"),
    (["lift", "--ckpt", "{ck}", "--scene", "{blender}", "--out", "{ck}/lift"], "{ck}/lift"),
    (["edit", "--ckpt", "{ck}", "--scene", "{blender}", "--label", "1", "--out", "{ck}"], "{ck}"),
    (["pet", "--ckpt", "{ck}", "--scene", "{blender}", "--out", "{blender}/pet"], "{blender}/pet"),
    (["bench", "--ckpt", "{ck}", "--out", "{ck}/r.json"], "{ck}/r.json"),
]

# Every command that loads a checkpoint, against every broken checkpoint (each command reads it its own way).
BAD_CKPTS = {"ck_no_config": "meta.json", "ck_five": "meta.json", "ck_preset": "meta.json", "ck_option": "meta.json",
             "ck_meta_list": "meta.json", "ck_meta_bad": "meta.json", "ck_shape": "meta.json",
             "ck_trunc": "model.safetensors", "ck_garbage": "model.safetensors", "ck_missing": "model.safetensors",
             "ck_nan": "model.safetensors", "ck_inf": "model.safetensors"}
CKPT_COMMANDS = {
    "eval": ["eval", "--scenes", "{with_test}", "--device", "cpu", "--out", "{out}", "--ckpt"],
    "mesh": ["mesh", "--scene", "{blender}", "--out", "{out}.ply", "--ckpt"],
    "export": ["export", "--scene", "{blender}", "--out", "{out}", "--ckpt"],
    "finetune": ["finetune", "--scene", "{blender}", "--out", "{out}", "--ckpt"],
    "lift": ["lift", "--scene", "{blender}", "--out", "{out}", "--ckpt"],
    "edit": ["edit", "--scene", "{blender}", "--label", "1", "--out", "{out}", "--ckpt"],
    "pet": ["pet", "--scene", "{blender}", "--out", "{out}", "--ckpt"],
    "bench": ["bench", "--out", "{out}.json", "--ckpt"],
}
ROWS += [([*args, f"{{{ck}}}"], f"{{{ck}}}/{f}") for args in CKPT_COMMANDS.values() for ck, f in BAD_CKPTS.items()]

# Every command that reads a scene, against broken scenes of each format.
BAD_SCENES = {"missing_image": "train/r_1.png", "corrupt_image": "train/r_2.png", "bad_json": "transforms_train.json",
              "nan_pose": "transforms_train.json", "outside_path": "transforms_train.json",
              "llff_bounds": "poses_bounds.npy", "neus_singular": "cameras_sphere.npz",
              "mvsnet_cam": "cams/00000001_cam.txt", "colmap_trunc": "sparse/0/images.bin"}
SCENE_COMMANDS = {
    "render": ["render", "--ckpt", "{ck}", "--out", "{out}", *RENDER, "--scene"],
    "mesh": ["mesh", "--model", "floor", "--out", "{out}.ply", "--scene"],
    "export": ["export", "--ckpt", "{ck_omni}", "--out", "{out}", "--scene"],
    "finetune": ["finetune", "--ckpt", "{ck_omni}", "--out", "{out}", "--scene"],
    "train": ["train", "--out", "{out}", *TRAIN, "--data"],
}
ROWS += [([*args, f"{{{s}}}"], f"{{{s}}}/{f}") for args in SCENE_COMMANDS.values() for s, f in BAD_SCENES.items()]


def _fill(text: str, paths: dict, out: Path) -> str:
    return text.replace("{out}", str(out)).format(**{k: str(v) for k, v in paths.items()})


def _ckpt_variants(root: Path) -> dict[str, Path]:
    from safetensors.torch import load_file, save_file

    from omnirecon.engine.checkpoint import save_checkpoint
    from omnirecon.models.registry import build_model

    good = root / "ck"
    torch.manual_seed(0)
    save_checkpoint(good, build_model("gpnr-tiny", TINY_GPNR), "gpnr-tiny")
    out = {"ck": good}

    def variant(name, meta=None, weights=None):
        d = root / name
        shutil.copytree(good, d)
        if meta is not None:
            m = json.loads((d / "meta.json").read_text())
            (d / "meta.json").write_text(json.dumps(meta(m)))
        if weights is not None:
            weights(d / "model.safetensors")
        out[name] = d

    def nonfinite(value):
        def edit(f):
            st = load_file(str(f))
            next(t for t in st.values() if t.is_floating_point() and t.numel() > 1).view(-1)[1] = value
            save_file(st, str(f))
        return edit

    def drop(m, key):
        m.pop(key)
        return m

    def set_(m, key, value):
        m["model_config"][key] = value
        return m

    variant("ck_no_config", lambda m: drop(m, "model_config"))
    variant("ck_five", lambda m: set_(m, "num_views", "five"))
    variant("ck_preset", lambda m: {**m, "preset": "gpnr-huge"})
    variant("ck_option", lambda m: set_(m, "warp_speed", 9))
    variant("ck_meta_list", lambda m: [m])
    variant("ck_meta_bad", lambda m: {**m, "step": "ten"})
    variant("ck_trunc", weights=lambda f: f.write_bytes(f.read_bytes()[: f.stat().st_size // 2]))
    variant("ck_garbage", weights=lambda f: f.write_bytes(b"\xff" * 64))
    variant("ck_missing", weights=lambda f: f.unlink())
    variant("ck_nan", weights=nonfinite(float("nan")))
    variant("ck_inf", weights=nonfinite(float("inf")))
    variant("ck_shape", lambda m: set_(m, "dim", 48))
    save_checkpoint(root / "ck_omni", build_model("omnirecon-tiny", {"coarse_samples": 4, "fine_samples": 2,
                                                                     "volume_resolution": 8}), "omnirecon-tiny")
    out["ck_omni"] = root / "ck_omni"
    return out


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory) -> dict[str, Path]:
    """Every malformed input of the table, built once (tiny: 8x8 images, 3 views)."""
    root = tmp_path_factory.mktemp("malformed")
    p: dict[str, Path] = {"root": root}
    (root / "empty").mkdir()
    p["empty"] = root / "empty"
    p["a_file"] = root / "a_file.txt"
    p["a_file"].write_text("not a folder")
    p["blender"] = blender_scene(root / "blender")
    p["small"] = p["blender"]
    s = p["with_test"] = blender_scene(root / "with_test")  # eval's blender protocol scores the test split
    shutil.copy(s / "transforms_train.json", s / "transforms_test.json")
    p["llff"] = llff_scene(root / "llff")
    s = p["missing_image"] = blender_scene(root / "missing_image")
    (s / "train" / "r_1.png").unlink()
    s = p["corrupt_image"] = blender_scene(root / "corrupt_image")
    (s / "train" / "r_2.png").write_bytes(b"not a png" * 10)
    s = p["bad_json"] = blender_scene(root / "bad_json")
    (s / "transforms_train.json").write_text('{"frames": [')
    mats = ring_gl().tolist()
    mats[1] = [row[:3] for row in mats[1][:3]]
    p["matrix_3x3"] = blender_scene(root / "matrix_3x3", mats=mats)
    mats = ring_gl().tolist()
    mats[2][0][3] = float("nan")
    p["nan_pose"] = blender_scene(root / "nan_pose", mats=mats)
    for name, rel in (("outside_path", "../outside"), ("absolute_path", str(root / "outside"))):
        s = p[name] = blender_scene(root / name)
        meta = json.loads((s / "transforms_train.json").read_text())
        meta["frames"][1]["file_path"] = rel
        (s / "transforms_train.json").write_text(json.dumps(meta))
    tiny_image(root / "outside.png")
    s = p["no_frames"] = blender_scene(root / "no_frames")
    (s / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": []}))
    p["llff_cols"] = llff_scene(root / "llff_cols", cols=16)
    s = p["llff_bounds"] = llff_scene(root / "llff_bounds")
    arr = np.load(s / "poses_bounds.npy")
    arr[1, 15:] = [5.0, 1.0]
    np.save(s / "poses_bounds.npy", arr)
    p["llff_rows"] = llff_scene(root / "llff_rows", images=4)
    s = p["llff_nan"] = llff_scene(root / "llff_nan")
    arr = np.load(s / "poses_bounds.npy")
    arr[0, 3] = np.inf
    np.save(s / "poses_bounds.npy", arr)
    P = np.eye(4)
    P[:3, :3] = [[10, 0, 4], [0, 10, 4], [0, 0, 1]]
    P[2, 3] = 3
    for name, mats in (("neus_keys", {f"world_mat_{i}": P for i in range(3)}),
                       ("neus_singular", {**{f"world_mat_{i}": P for i in range(3)}, "world_mat_1": np.zeros((4, 4)),
                                          **{f"scale_mat_{i}": np.eye(4) for i in range(3)}})):
        s = p[name] = root / name
        for i in range(3):
            tiny_image(s / "image" / f"{i:06d}.png", seed=i)
        np.savez(s / "cameras_sphere.npz", **mats)
    s = p["mvsnet_cam"] = root / "mvsnet_cam"
    for i in range(3):
        tiny_image(s / "images" / f"{i:08d}.png", seed=i)
        (s / "cams").mkdir(parents=True, exist_ok=True)
        (s / "cams" / f"{i:08d}_cam.txt").write_text(
            "extrinsic\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n\nintrinsic\n10 0 4\n0 10 4\n0 0 1\n\n1 0.1\n")
    (s / "cams" / "00000001_cam.txt").write_text("extrinsic\n1 0 0\n")
    s = p["colmap_trunc"] = colmap_scene(root / "colmap_trunc", ext=".bin")
    f = s / "sparse" / "0" / "images.bin"
    f.write_bytes(f.read_bytes()[:50])
    s = p["colmap_outside"] = colmap_scene(root / "colmap_outside")
    f = s / "sparse" / "0" / "images.txt"
    f.write_text(f.read_text().replace("im1.png", "../../outside.png"))
    p.update(_ckpt_variants(root))
    run = p["run_broken"] = root / "run_broken"  # a run folder whose only checkpoint is truncated
    shutil.copytree(p["ck_trunc"], run / "checkpoints" / "step_0000002")
    os.symlink("step_0000002", run / "checkpoints" / "latest")
    return p


def _tree(root: Path) -> set[str]:
    return {str(q.relative_to(root)) for q in root.rglob("*")}


@pytest.mark.parametrize("args, named", ROWS, ids=[f"{i:03d}-{' '.join(r[0][:1] + r[0][1:3])[:40]}"
                                                    for i, r in enumerate(ROWS)])
def test_malformed_input(fixtures, tmp_path, monkeypatch, capsys, args, named):
    monkeypatch.chdir(tmp_path)  # default outputs/ of a command would land here
    out = tmp_path / "out"
    argv = [_fill(a, fixtures, out) for a in args]
    before = _tree(fixtures["root"])
    capsys.readouterr()
    rc = main(argv)
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 2, (argv, rc, err)
    assert len(lines) == 1 and lines[0].startswith("omnirecon: error: ") and "Traceback" not in err, err
    assert "(fix: " in lines[0], lines[0]
    print(lines[0])  # shown with pytest -rP: the table of messages
    if named is not None:
        assert _fill(named, fixtures, out) in lines[0], lines[0]
    leftovers = [p for p in out.parent.glob(out.name + "*")]
    assert not leftovers, leftovers
    assert _tree(fixtures["root"]) == before, _tree(fixtures["root"]) ^ before
    assert not (tmp_path / "outputs").exists() or not any((tmp_path / "outputs").rglob("*")), "wrote under outputs/"


def test_table_covers_every_command():
    """Each command of the CLI has rows (a new command must add its own)."""
    from omnirecon.cli import COMMANDS

    covered = {r[0][0] for r in ROWS}
    assert set(COMMANDS) - {"doctor"} <= covered, set(COMMANDS) - covered  # doctor takes no input files
