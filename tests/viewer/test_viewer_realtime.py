"""The viewer bundle holds MeshRenderer's real-time setting (every training view, the per-scene blend and fills, the
sources' object masks), `omnirecon view` refuses a bundle of another version, and headless Chromium draws each part
of the setting as MeshRenderer draws it: the angle blend weighted by the source masks, the nearest fill, the crack fill,
and the network blend over each frame's nearest sources."""

import io
import json
import urllib.parse

import numpy as np
import pytest
import torch
import trimesh
from conftest import ROOT, require, viewer_scene

from bench.viewer_parity import input_camera, psnr8, python_frames
from omnirecon.cli import main
from omnirecon.engine.checkpoint import load_checkpoint
from omnirecon.engine.scenes import load_at_resolution
from omnirecon.engine.views import select_sources
from omnirecon.mesh.files import read_mesh, to_input_frame
from omnirecon.mesh.ibr import realtime_setting
from omnirecon.viewer.bundle import mask_table, three_unavailable_reason
from omnirecon.viewer.export import ExportOptions, export_scene
from omnirecon.viewer.headless import find_chromium

CKPT = ROOT / "checkpoints" / "omnirecon-tiny"
TARGET = 7  # the procedural scene's test view
SCALE = 2.0  # drawn at 128 x 128
MIN_PSNR = 33.0
"""Browser against MeshRenderer: above what any part of the setting changes in this scene (26-29 dB: measured below)."""


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A procedural scene made to look like a real capture with object masks (no known background colour: the angle
    blend, source masks and the nearest fill by default), its exact mesh with 5 % of the faces removed (cracks),
    omnirecon-tiny, and two exports: the scene's default setting, and the network blend over each frame's 3 nearest of
    the 6 training views."""
    tmp, scene_path, scene = viewer_scene(tmp_path_factory, "realtime")
    scene.background = None  # a real object capture with masks, as DTU
    exact = to_input_frame(read_mesh(scene.mesh_path), torch.linalg.inv(scene.to_input.double()))  # model frame
    keep = np.random.default_rng(0).random(len(exact.faces)) > 0.05
    holed = trimesh.Trimesh(exact.vertices, exact.faces[keep], process=False)
    mesh_in = to_input_frame(holed, scene.to_input.double())  # export takes the input frame
    model = load_checkpoint(CKPT)[0].eval()
    views = scene.splits["train"]
    export_scene(model, scene, views, tmp / "angle", mesh_in)
    network = ExportOptions(blend="network", fill="background", frame_sources=3)
    export_scene(model, scene, views, tmp / "network", mesh_in, options=network)
    return {"scene": scene, "scene_path": scene_path, "mesh": holed, "mesh_in": mesh_in, "model": model,
            "views": views, "tmp": tmp, "network": network.setting(scene)}


def test_bundle_holds_the_realtime_setting_and_the_masks(exported):
    scene, tmp = exported["scene"], exported["tmp"]
    meta = json.loads((tmp / "angle" / "viewer" / "bundle.json").read_text())
    setting = realtime_setting(scene)
    assert meta["version"] == 2 and meta["setting"] == setting and setting["blend"] == "angle"
    assert meta["sources"]["views"] == scene.splits["train"] and meta["sources"]["count"] == 6
    assert meta["fill"]["default"] == "nearest" and meta["cracks"] == 2 and meta["source_masks"]["default"]
    K, H, W = 6, scene.height, scene.width
    rgba = np.frombuffer((tmp / "angle" / "viewer" / "images.bin").read_bytes(), np.uint8).reshape(K, H, W, 4)
    masks = scene.masks[scene.splits["train"]]
    np.testing.assert_array_equal(rgba[..., 3], mask_table(masks, (K, H, W)))
    assert (rgba[..., 3][~masks.numpy()] == 0).all() and rgba[..., 3].max() > 4  # off the mask 0, inside d^2
    cams = np.frombuffer((tmp / "angle" / "viewer" / "cameras.bin").read_bytes(), "<f4").reshape(K, 4, 4)
    np.testing.assert_allclose(cams[:, :3], np.asarray(meta["sources"]["proj"])[:, :3], rtol=0, atol=0)
    np.testing.assert_allclose(cams[:, 3, :3], np.asarray(meta["sources"]["centers"]), rtol=0, atol=1e-6)
    net = json.loads((tmp / "network" / "viewer" / "bundle.json").read_text())
    assert net["blend"]["default"] == "network" and net["blend"]["frame_sources"] == 3
    assert net["blend"]["metric"] == "angle" and net["fill"]["default"] == "background"


def test_export_takes_every_train_view_or_the_finetune_record(exported, tmp_path, run_cli):
    """`omnirecon export` puts every train view in the bundle and starts it with the scene's real-time setting; with
    --finetune, the record's sources and setting; a bad record is one line."""
    from omnirecon.engine.checkpoint import save_checkpoint

    ckpt = tmp_path / "ckpt"
    save_checkpoint(ckpt, exported["model"], "omnirecon-tiny")
    exported["mesh_in"].export(tmp_path / "mesh.ply")
    base = ["export", "--scene", exported["scene_path"], "--ckpt", ckpt, "--mesh", tmp_path / "mesh.ply", "--threads", 1]
    code, _, err = run_cli([*base, "--out", tmp_path / "plain"])
    assert code == 0, err
    meta = json.loads((tmp_path / "plain" / "viewer" / "bundle.json").read_text())
    scene = load_at_resolution(exported["scene_path"], 64)  # as export reads it: the procedural background colour
    assert meta["sources"]["views"] == scene.splits["train"] and meta["setting"] == realtime_setting(scene)
    render = {"blend": "angle", "fill": "far", "sources": 0, "angle_sources": 3, "source_masks": False, "cracks": 1}
    (tmp_path / "ft").mkdir()
    (tmp_path / "ft" / "curve.json").write_text(json.dumps({"sources": [0, 2, 4, 5], "render": render,
                                                            "resolution": [64, 64]}))
    code, _, err = run_cli([*base, "--finetune", tmp_path / "ft", "--out", tmp_path / "tuned"])
    assert code == 0, err
    meta = json.loads((tmp_path / "tuned" / "viewer" / "bundle.json").read_text())
    assert meta["sources"]["views"] == [0, 2, 4, 5] and meta["setting"] == {**render, "soften": 0}  # a record from before
    (tmp_path / "ft" / "curve.json").write_text("{not json")
    code, _, err = run_cli([*base, "--finetune", tmp_path / "ft", "--out", tmp_path / "bad"])
    assert code == 2 and "curve.json" in err and "\n" not in err.strip(), err


def test_view_refuses_a_bundle_of_another_version(exported, tmp_path, capsys):
    import shutil

    old = tmp_path / "old"
    shutil.copytree(exported["tmp"] / "angle" / "viewer", old)
    meta = json.loads((old / "bundle.json").read_text())
    (old / "bundle.json").write_text(json.dumps({**meta, "version": 1}))
    assert main(["view", str(old), "--no-browser", "--port", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert "bundle.json" in err and "version 1" in err and "re-export" in err and "\n" not in err, err


def browser_missing() -> str | None:
    if find_chromium() is None:
        return "no chromium on PATH (Debian: apt-get install chromium; scripts/setup_system.sh does)"
    return three_unavailable_reason()


@pytest.mark.slow
def test_browser_draws_each_part_of_the_realtime_setting(exported):
    """At the held-out camera, the browser's frame matches MeshRenderer's with the same setting (>= 33 dB), for the
    scene's default (angle blend, source masks, nearest fill, cracks) and with each part turned off, and every part
    changes MeshRenderer's frame by more than the browser misses it by; the network blend takes each frame's 3 nearest
    of the 6 sources, as select_sources picks them."""
    reason = browser_missing()
    require(not reason, str(reason))
    from PIL import Image

    from omnirecon.viewer.headless import HeadlessChromium
    from omnirecon.viewer.server import ViewerServer

    scene, model, mesh, views, tmp = (exported[k] for k in ("scene", "model", "mesh", "views", "tmp"))
    setting = {**realtime_setting(scene), "soften": 0.0}  # the viewer does not blur depth edges (finetune --soften)
    variants = {"default": ("1", {}), "no masks": ("omnirecon.setMasks(false)", {"source_masks": False}),
                "far": ("omnirecon.setMasks(true), omnirecon.setFill('far')", {"fill": "far"}),
                "far, no cracks": ("omnirecon.setCracks(false)", {"fill": "far", "cracks": 0}),
                "background, cracks": ("omnirecon.setCracks(true), omnirecon.setFill('background')",
                                       {"fill": "background"})}
    refs = {name: python_frames(model, mesh, scene, [TARGET], views, {**setting, **change}, scale=SCALE)[0][0]
            for name, (_, change) in variants.items()}
    network = {**exported["network"], "soften": 0.0}
    net_ref = python_frames(model, mesh, scene, [TARGET], views, network, "pool", SCALE)[0][0]
    every = python_frames(model, mesh, scene, [TARGET], views, {**network, "sources": 0}, None, SCALE)[0][0]
    camera = input_camera(scene, TARGET, SCALE)
    W, H = camera["width"], camera["height"]
    scores, picks = {}, {}
    with HeadlessChromium(W, H, timeout=60) as browser:
        def shot() -> np.ndarray:
            png = browser.screenshot(None, W, H, redraw="omnirecon.render(), 1")
            return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))

        for bundle in ("angle", "network"):
            server = ViewerServer(tmp / bundle / "viewer", port=0, quiet=True)
            server.start()
            try:
                browser.goto(server.url + "index.html?" + urllib.parse.urlencode({"camera": json.dumps(camera)}))
                state = browser.wait_for("document.documentElement.dataset.state !== 'loading' && "
                                         "document.documentElement.dataset.state")
                assert state == "ready", (browser.evaluate("document.documentElement.dataset.error"), browser.console())
                assert browser.evaluate("omnirecon.info.mode") == "ibr", browser.evaluate("omnirecon.info")
                if bundle == "angle":
                    for name, (js, _) in variants.items():
                        browser.evaluate(f"{js}, 1")
                        scores[name] = psnr8(shot(), refs[name])
                    continue
                scores["network, 3 per frame"] = psnr8(shot(), net_ref)
                for t in range(len(scene)):  # the viewer's picks against select_sources, at every camera of the scene
                    cam = {**input_camera(scene, t, SCALE), "frame": "input"}
                    picks[t] = browser.evaluate(f"omnirecon.viewer.frameSources(omnirecon.viewer.toModelCamera("
                                                f"{json.dumps(cam)}))")
            finally:
                server.stop()
    print(f"browser vs MeshRenderer PSNR: {scores}")
    assert all(s >= MIN_PSNR for s in scores.values()), scores
    changed = {name: psnr8(refs[name], refs["default"]) for name in variants if name != "default"}
    changed["far, no cracks vs far"] = psnr8(refs["far, no cracks"], refs["far"])
    changed["network, every source"] = psnr8(every, net_ref)
    print(f"MeshRenderer, each part off against on: {changed}")
    assert all(c < MIN_PSNR for c in changed.values()), changed
    want = {t: sorted(views.index(v) for v in select_sources(scene, scene.cameras[t], views, 3)) for t in picks}
    assert picks == want
