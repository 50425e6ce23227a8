"""Export with baked vertex colours, the viewer bundle, `omnirecon view`'s server, and the WebGL viewer in
headless Chromium against the Python mesh renderer (PSNR >= 30 dB at a fixed held-out camera)."""

import io
import json
import os
import shutil
import socket
import urllib.parse
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from conftest import ROOT, require

from omnirecon.cli import main
from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.engine.checkpoint import load_checkpoint, save_checkpoint
from omnirecon.engine.scenes import load_at_resolution
from omnirecon.mesh.files import linear_to_srgb, read_mesh, srgb_to_linear, to_input_frame
from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions
from omnirecon.models.registry import build_model
from omnirecon.rays import Sources
from omnirecon.render.raster import MeshRasterizer
from omnirecon.viewer.bundle import three_unavailable_reason
from omnirecon.viewer.export import ExportOptions, export_scene
from omnirecon.viewer.headless import find_chromium
from omnirecon.viewer.server import ViewerServer, bundle_folder

SOURCES = [1, 2, 3, 5]
TARGET = 7  # the scene's test view
MIN_PSNR = 30.0


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(max(float(((a - b) ** 2).mean()), 1e-12)))


def browser_missing() -> str | None:
    if find_chromium() is None:
        return "no chromium on PATH (Debian: apt-get install chromium; scripts/setup_system.sh does)"
    return three_unavailable_reason()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A procedural scene, its exact mesh (input frame), omnirecon-tiny (shipped checkpoint, else seeded
    random weights) and the export of all three with 4 sources."""
    tmp = tmp_path_factory.mktemp("viewer")
    scene_path = generate_scene(tmp / "scenes", 0, SynthOptions(resolution=64, views=8))
    scene = load_at_resolution(scene_path, 64)
    mesh = read_mesh(scene.mesh_path)  # the procedural scene's mesh file is in its input frame
    ckpt = ROOT / "checkpoints" / "omnirecon-tiny"
    if (ckpt / "meta.json").is_file():
        model, _ = load_checkpoint(ckpt)
    else:
        torch.manual_seed(0)
        model = build_model("omnirecon-tiny")
    model.eval()
    viewer = three_unavailable_reason() is None
    record = export_scene(model, scene, SOURCES, tmp / "out", mesh, options=ExportOptions(viewer=viewer, angle_sources=3))
    return {"scene": scene, "scene_path": scene_path, "mesh": mesh, "model": model, "out": tmp / "out",
            "record": record, "tmp": tmp}


def test_export_writes_ply_and_glb_with_vertex_colours(exported):
    out, mesh = exported["out"], exported["mesh"]
    loaded = {}
    for name in ("mesh.ply", "mesh.glb"):
        m = trimesh.load(out / name, process=False, force="mesh")
        colours = np.asarray(m.visual.vertex_colors)
        assert m.visual.kind == "vertex" and colours.shape == (len(m.vertices), 4) == (len(mesh.vertices), 4)
        np.testing.assert_allclose(m.vertices, mesh.vertices, atol=1e-5)  # input frame, vertex order kept
        np.testing.assert_array_equal(m.faces, mesh.faces)
        loaded[name] = colours
    # PLY keeps sRGB bytes; glTF's COLOR_0 is linear
    lin = np.round(srgb_to_linear(loaded["mesh.ply"][:, :3] / 255.0) * 255)
    np.testing.assert_array_equal(loaded["mesh.glb"][:, :3], lin)
    np.testing.assert_array_equal(loaded["mesh.glb"][:, 3], loaded["mesh.ply"][:, 3])
    assert (loaded["mesh.glb"][:, :3] <= loaded["mesh.ply"][:, :3]).all()
    assert (loaded["mesh.ply"][:, 3] == 255).all() and loaded["mesh.ply"][:, :3].std() > 10
    record = json.loads((out / "export.json").read_text())
    assert record["vertices"] == len(mesh.vertices) and record["frame"] == "input"
    assert record["bake"]["unseen"] < 0.01 * len(mesh.vertices)


def test_baked_colours_follow_the_images(exported):
    """The baked mesh drawn at a held-out view looks like the ground-truth image. Vertex colours are only as
    fine as the vertices: the procedural ground is a few large triangles, so --max-edge subdivision must
    bring the texture back (pixels no source sees stay background in both)."""
    scene, model, tmp = exported["scene"], exported["model"], exported["tmp"]
    cam = scene.cameras[TARGET].to(dtype=torch.float32)
    gt = scene.images[TARGET].numpy()
    coarse = psnr(baked_reference(exported["out"], scene, cam), gt)
    record = export_scene(model, scene, SOURCES, tmp / "fine", exported["mesh"],
                          options=ExportOptions(viewer=False, max_edge=0.01))
    assert record["faces"] > 2 * len(exported["mesh"].faces) and record["mesh"]["subdivided"]
    fine = psnr(baked_reference(tmp / "fine", scene, cam), gt)
    assert fine > 16 and fine > coarse + 2, (coarse, fine)  # measured 13.8 -> 17.7 dB


def baked_reference(out: Path, scene, cam) -> np.ndarray:
    """The exported (linear) vertex colours interpolated per pixel (perspective-correct barycentrics) and
    encoded to sRGB, as the viewer's baked mode draws them. ``# [H, W, 3]``"""
    glb = trimesh.load(out / "mesh.glb", process=False, force="mesh")
    mm = to_input_frame(glb, torch.linalg.inv(scene.to_input.double()))
    colours = torch.from_numpy(np.asarray(glb.visual.vertex_colors)[:, :3] / 255.0)  # linear
    g = MeshRasterizer.from_trimesh(mm).rasterize(cam, normals="none")
    img = torch.tensor(scene.background, dtype=torch.float64).expand(cam.height, cam.width, 3).clone()
    hit = g.mask
    faces = torch.from_numpy(np.asarray(mm.faces))[g.face[hit]]  # [P, 3]
    img[hit] = torch.from_numpy(linear_to_srgb((g.bary[hit].double()[:, :, None] * colours[faces]).sum(1).numpy()))
    return img.numpy()


# ---------------------------------------------------------------------- the server
def raw_get(port: int, target: str, method: str = "GET") -> tuple[int, bytes]:
    """Send a request line exactly as given (no client-side normalisation); status and body."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(f"{method} {target} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n".encode())
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), body


def test_server_refuses_paths_outside_its_folder(tmp_path):
    root = tmp_path / "bundle"
    (root / "sub").mkdir(parents=True)
    (root / "index.html").write_text("<p>viewer</p>")
    (root / "sub" / "data.bin").write_bytes(b"\x00\x01")
    secret = tmp_path / "secret.txt"
    secret.write_text("TOP SECRET")
    os.symlink(secret, root / "link.txt")
    os.symlink(tmp_path, root / "up")
    server = ViewerServer(root, port=0, quiet=True)
    server.start()
    try:
        port = server.server_address[1]
        assert server.url.startswith("http://127.0.0.1:")
        assert raw_get(port, "/index.html") == (200, b"<p>viewer</p>")
        assert raw_get(port, "/") == (200, b"<p>viewer</p>")
        assert raw_get(port, "/sub/data.bin?x=1")[0] == 200
        refused = ["/../secret.txt", "/sub/../../secret.txt", "/%2e%2e/secret.txt", "/..%2fsecret.txt",
                   "/sub/%2E%2E/%2E%2E/secret.txt", "/..\\secret.txt", f"/{'/'.join(['..'] * 8)}{secret}",
                   str(secret), f"/{secret}", "//" + str(secret).lstrip("/"), f"http://127.0.0.1{secret}",
                   "/link.txt", "/up/secret.txt", "/etc/passwd", "/sub/"]
        for target in refused:
            status, body = raw_get(port, target)
            assert status == 404, (target, status)  # one answer for refused and missing alike
            assert b"TOP SECRET" not in body, target
        assert raw_get(port, "/index.html", "POST")[0] == 405
    finally:
        server.stop()


def test_view_finds_the_bundle_and_rejects_bad_input(exported, tmp_path, capsys):
    require(not three_unavailable_reason(), str(three_unavailable_reason()))
    assert bundle_folder(exported["out"]) == exported["out"] / "viewer"
    assert main(["view", str(tmp_path / "missing"), "--no-browser"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("omnirecon: error:") and "\n" not in err


def test_export_cli(exported, tmp_path, capsys):
    """`omnirecon export` end to end with a saved checkpoint and --mesh; one-line errors for bad input."""
    ckpt = tmp_path / "ckpt"
    save_checkpoint(ckpt, exported["model"], "omnirecon-tiny")
    mesh_file = tmp_path / "input.ply"
    exported["mesh"].export(mesh_file)
    base = ["export", "--scene", str(exported["scene_path"]), "--ckpt", str(ckpt), "--views", *map(str, SOURCES),
            "--threads", "1", "--device", "cpu"]
    viewer = [] if three_unavailable_reason() is None else ["--no-viewer"]
    assert main([*base, "--mesh", str(mesh_file), "--out", str(tmp_path / "out"), *viewer]) == 0
    capsys.readouterr()
    ply = trimesh.load(tmp_path / "out" / "mesh.ply", process=False)
    assert len(ply.visual.vertex_colors) == len(exported["mesh"].vertices)
    if not viewer:
        files = {p.relative_to(tmp_path / "out" / "viewer").as_posix() for p in (tmp_path / "out" / "viewer").rglob("*")}
        assert {"index.html", "viewer.js", "bundle.json", "mesh.glb", "images.bin", "features.bin", "depth.bin",
                "lib/three/build/three.module.js"} <= files
    for bad, words in ([["--mesh", str(tmp_path / "nope.ply")], "mesh file not found"],
                       [["--mesh", str(mesh_file), "--bake-views", "0"], "--bake-views"],
                       [["--mesh", str(ckpt / "meta.json")], "cannot read the mesh"]):
        assert main([*base, *bad, "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("omnirecon: error:") and words in err and "\n" not in err, err
    gpnr = ROOT / "checkpoints" / "gpnr-tiny"
    if gpnr.is_dir():
        args = ["export", "--scene", str(exported["scene_path"]), "--ckpt", str(gpnr), "--views", *map(str, SOURCES),
                "--mesh", str(mesh_file), "--out", str(tmp_path / "bad"), "--no-viewer"]
        assert main(args) == 2
        assert "appearance branch" in capsys.readouterr().err


# ---------------------------------------------------------------------- the browser
@pytest.mark.slow
def test_browser_viewer_matches_python_renderer(exported, tmp_path):
    """Headless Chromium (software WebGL2) draws the exported bundle at a fixed held-out camera, given in
    the input frame; the screenshot matches MeshRenderer.render for the same camera (visibility test
    on and off, the far fill on and off, the network and the angle blend) and the baked mode matches the vertex colours drawn in Python; without the float
    feature texture the viewer falls back to the baked colours by itself."""
    reason = browser_missing()
    require(not reason, str(reason))
    from PIL import Image

    from omnirecon.viewer.headless import HeadlessChromium

    scene, model, out = exported["scene"], exported["model"], exported["out"]
    cam = scene.cameras[TARGET].to(dtype=torch.float32).rescaled(2.0)  # 128 x 128
    mm = to_input_frame(exported["mesh"], torch.linalg.inv(scene.to_input.double()))
    sources = Sources.from_scene(scene, SOURCES)
    refs = {}
    for vis in (True, False):  # a procedural scene with a background colour: the bundle's fill starts off
        opts = MeshRenderOptions(background=scene.background, visibility=vis, fill="background")
        with MeshRenderer(model, mm, sources, opts) as r:
            refs[vis] = r.render(cam)["rgb"].numpy()
    with MeshRenderer(model, mm, sources, MeshRenderOptions(background=scene.background, visibility=True)) as r:
        refs["fill"], uncovered = r.render(cam)["rgb"].numpy(), ~r.render(cam)["mask"].numpy()
    angle = MeshRenderOptions(background=scene.background, visibility=True, blend="angle", angle_sources=3)
    with MeshRenderer(model, mm, sources, angle) as r:
        refs["angle_fill"] = r.render(cam)["rgb"].numpy()
    assert uncovered.mean() > 0.2  # the fill shades a good part of the view
    refs["baked"] = baked_reference(out, scene, cam)
    cam_in = cam.to(dtype=torch.float64).transformed(scene.to_input)  # what a user passes: the input frame
    camera = {"fx": float(cam_in.fx[0]), "fy": float(cam_in.fy[0]), "cx": float(cam_in.cx[0]),
              "cy": float(cam_in.cy[0]), "width": cam.width, "height": cam.height, "c2w": cam_in.c2w[0].tolist()}
    broken = tmp_path / "broken"  # a bundle without its float feature texture
    shutil.copytree(out / "viewer", broken)
    (broken / "features.bin").unlink()
    server = ViewerServer(out / "viewer", port=0, quiet=True)
    server.start()
    broken_server = ViewerServer(broken, port=0, quiet=True)
    broken_server.start()
    scores = {}
    try:
        with HeadlessChromium(cam.width, cam.height, timeout=30) as browser:
            def shot(url: str, expect_mode: str) -> np.ndarray:
                browser.goto(url)
                state = browser.wait_for("document.documentElement.dataset.state !== 'loading' && "
                                         "document.documentElement.dataset.state")
                assert state == "ready", (browser.evaluate("document.documentElement.dataset.error"), browser.console())
                info = browser.evaluate("omnirecon.info")
                assert info["mode"] == expect_mode and (info["width"], info["height"]) == (cam.width, cam.height), info
                png = browser.screenshot(None, cam.width, cam.height, redraw="omnirecon.render(), 1")
                return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.float64) / 255

            query = {"camera": json.dumps(camera)}
            url = server.url + "index.html?" + urllib.parse.urlencode({**query, "vis": "1"})
            scores["ibr_visibility"] = psnr(shot(url, "ibr"), refs[True])
            browser.evaluate("omnirecon.setVisibility(false), 1")
            png = browser.screenshot(None, cam.width, cam.height, redraw="omnirecon.render(), 1")
            img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.float64) / 255
            scores["ibr"] = psnr(img, refs[False])
            fps = browser.evaluate("omnirecon.benchmark(10)")
            url = server.url + "index.html?" + urllib.parse.urlencode({**query, "vis": "1", "fill": "1"})
            scores["ibr_fill"] = psnr(shot(url, "ibr"), refs["fill"])
            browser.evaluate("omnirecon.setBlend('angle'), 1")  # the bundle's angle_sources: 3 (export_scene)
            png = browser.screenshot(None, cam.width, cam.height, redraw="omnirecon.render(), 1")
            img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.float64) / 255
            scores["ibr_angle_fill"] = psnr(img, refs["angle_fill"])
            url = server.url + "index.html?" + urllib.parse.urlencode({**query, "mode": "baked"})
            scores["baked"] = psnr(shot(url, "baked"), refs["baked"])
            url = broken_server.url + "index.html?" + urllib.parse.urlencode(query)
            scores["fallback"] = psnr(shot(url, "baked"), refs["baked"])
            assert "features.bin" in browser.evaluate("omnirecon.info.fallback")
    finally:
        server.stop()
        broken_server.stop()
    print(f"browser vs Python PSNR: {scores}; viewer {fps['fps']:.0f} FPS at {fps['width']}x{fps['height']} ({fps['mode']})")
    assert all(s >= MIN_PSNR for s in scores.values()), scores
    assert psnr(refs[True], refs["baked"]) < min(scores.values())  # the modes differ: each matched its own
    assert psnr(refs[True], refs["fill"]) < min(scores.values())  # and so do fill and background
    assert psnr(refs["fill"], refs["angle_fill"]) < min(scores.values())  # and the two blends
