"""The viewer bundle of a fine-tuned checkpoint carries the tuned appearance: its tables differ from the
pretrained model's bundle, equal the tuned model's own (the ones ``MeshRenderer`` shades with), and the
browser draws what the Python renderer draws with the tuned model."""

import io
import json
import urllib.parse

import numpy as np
import pytest
import torch
from conftest import ROOT, require, viewer_scene

from omnirecon.engine.checkpoint import load_checkpoint
from omnirecon.mesh.files import read_mesh, to_input_frame
from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions
from omnirecon.rays import Sources
from omnirecon.viewer.bundle import appearance_tables
from omnirecon.viewer.export import ExportOptions, export_scene
from omnirecon.viewer.headless import find_chromium
from omnirecon.viewer.server import ViewerServer
from omnirecon.workflows.finetune import FinetuneConfig, run_finetune

SOURCES = [1, 2, 3, 5]
TARGET = 7
CKPT = ROOT / "checkpoints" / "omnirecon-tiny"


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    """A procedural scene and its exact mesh; the shipped omnirecon-tiny tuned on it for a few seconds
    (`omnirecon finetune --save`, 3 CPU-s: a wall budget on a loaded machine left too few steps to beat the start on
    validation); the export of the pretrained and of the tuned checkpoint."""
    tmp, scene_path, scene = viewer_scene(tmp_path_factory, "tuned")
    tuned = run_finetune(FinetuneConfig(ckpt=CKPT, scene=scene_path, seconds=3.0, clock="cpu", eval_at=(0.0, 3.0),
                                        mesh=scene.mesh_path, resolution=64, max_held_out=1, save=True,
                                        out=tmp / "finetune", threads=1))
    mesh = read_mesh(scene.mesh_path)
    models = {"pretrained": load_checkpoint(CKPT)[0].eval(),
              "tuned": load_checkpoint(tmp / "finetune" / "checkpoint")[0].eval()}
    for name, model in models.items():
        export_scene(model, scene, SOURCES, tmp / name, mesh, options=ExportOptions())
    return {"scene": scene, "mesh": mesh, "models": models, "tmp": tmp, "curve": tuned["curve"]}


def _bundle(folder):
    meta = json.loads((folder / "viewer" / "bundle.json").read_text())
    features = np.frombuffer((folder / "viewer" / "features.bin").read_bytes(), "<f4")
    return meta, features.reshape(meta["textures"]["features"]["shape"])


def test_tuned_bundle_differs_and_holds_the_tuned_tables(bundles):
    tmp, scene, mesh = bundles["tmp"], bundles["scene"], bundles["mesh"]
    (meta_p, feat_p), (meta_t, feat_t) = _bundle(tmp / "pretrained"), _bundle(tmp / "tuned")
    assert feat_p.shape == feat_t.shape and np.abs(feat_p - feat_t).max() > 1e-4  # tuned features differ
    mm = to_input_frame(mesh, torch.linalg.inv(scene.to_input.double()))
    sources = Sources.from_scene(scene, SOURCES)
    with MeshRenderer(bundles["models"]["tuned"], mm, sources, MeshRenderOptions(visibility=True)) as r:
        tables = appearance_tables(r)  # what the Python renderer shades with
    np.testing.assert_allclose(feat_t, tables["features"], atol=1e-6)
    for key in ("w1", "b1", "w2", "b2", "w3", "b3"):
        np.testing.assert_allclose(np.asarray(meta_t["mlp"][key]), np.asarray(tables["mlp"][key]), atol=1e-7)
    changed = any(not np.allclose(np.asarray(meta_p["mlp"][k]), np.asarray(meta_t["mlp"][k]))
                  for k in ("w1", "b1", "w2", "b2", "w3", "b3"))
    assert changed  # the appearance MLP was tuned too, and the bundle carries it


@pytest.mark.slow
def test_browser_draws_the_tuned_appearance(bundles):
    """Headless Chromium draws the tuned bundle as MeshRenderer draws the tuned model (>= 30 dB), and
    farther from the pretrained model's render than from the tuned one."""
    require(find_chromium() is not None, "no chromium on PATH (scripts/setup_system.sh installs it)")
    from PIL import Image

    from omnirecon.viewer.headless import HeadlessChromium

    scene, tmp = bundles["scene"], bundles["tmp"]
    cam = scene.cameras[TARGET].to(dtype=torch.float32).rescaled(2.0)
    mm = to_input_frame(bundles["mesh"], torch.linalg.inv(scene.to_input.double()))
    sources = Sources.from_scene(scene, SOURCES)
    refs = {}
    for name, model in bundles["models"].items():
        opts = MeshRenderOptions(background=scene.background, visibility=True)  # the far fill, as the viewer's fill=1
        with MeshRenderer(model, mm, sources, opts) as r:
            refs[name] = r.render(cam)["rgb"].numpy()
    cam_in = cam.to(dtype=torch.float64).transformed(scene.to_input)
    camera = {"fx": float(cam_in.fx[0]), "fy": float(cam_in.fy[0]), "cx": float(cam_in.cx[0]),
              "cy": float(cam_in.cy[0]), "width": cam.width, "height": cam.height, "c2w": cam_in.c2w[0].tolist()}
    server = ViewerServer(tmp / "tuned" / "viewer", port=0, quiet=True)
    server.start()
    try:
        with HeadlessChromium(cam.width, cam.height, timeout=30) as browser:
            browser.goto(server.url + "index.html?" + urllib.parse.urlencode({"camera": json.dumps(camera), "vis": "1",
                                                                                 "fill": "1"}))
            state = browser.wait_for("document.documentElement.dataset.state !== 'loading' && "
                                     "document.documentElement.dataset.state")
            assert state == "ready", browser.console()
            png = browser.screenshot(None, cam.width, cam.height, redraw="omnirecon.render(), 1")
    finally:
        server.stop()
    shot = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.float64) / 255

    def psnr(a, b):
        return float(-10 * np.log10(max(float(((a - b) ** 2).mean()), 1e-12)))

    tuned, pretrained = psnr(shot, refs["tuned"]), psnr(shot, refs["pretrained"])
    print(f"browser vs Python, tuned model {tuned:.2f} dB, pretrained model {pretrained:.2f} dB")
    assert tuned >= 30.0 and tuned > pretrained, (tuned, pretrained)
