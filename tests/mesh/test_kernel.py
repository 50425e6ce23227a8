"""One mesh-path blend: the weight functions are defined once (``omnirecon.mesh.kernel``), and the real-time renderer
(``MeshRenderer``: fused shader and reference path) and finetune's scores and tuning steps (``omnirecon.mesh.pixels``)
give the same colours at the same pixels of a procedural scene, the tuner's with gradients."""

import ast
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from conftest import ROOT

from omnirecon.data import load_scene
from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.mesh import kernel
from omnirecon.mesh.ibr import MeshRenderer, MeshRenderOptions
from omnirecon.mesh.pixels import angle_blend, encode_maps, point_colours, rasterize_views, render_pixels
from omnirecon.models.registry import build_model
from omnirecon.rays import Sources

SOURCES = [1, 2, 3, 5, 6]

BLEND_FUNCTIONS = ("block_depth_max", "unoccluded", "lumigraph", "lumigraph_weights", "angle_weights",
                   "angle_blend_weights", "mask_falloff", "mask_factor", "apply_mask_factor", "consensus_weights",
                   "blend_colours")
"""The kernel's weight and colour functions (``omnirecon.mesh.kernel``)."""
FORMULAS = {"lumigraph": ".clamp_min(0) / ", "consensus_weights": "(rgb - m) ** 2"}
"""A fragment of each formula's code (as ``ast.unparse`` writes it) that only its kernel function may hold."""


def code_of(path: Path) -> dict[str, str]:
    """``{qualified function name: its code without docstrings}`` of one module."""
    tree = ast.parse(path.read_text())
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body[1:] if (node.body and isinstance(node.body[0], ast.Expr)
                                     and isinstance(node.body[0].value, ast.Constant)) else node.body
            out[node.name] = "\n".join(ast.unparse(s) for s in body)
    return out


def test_each_blend_function_and_formula_is_defined_once_in_the_kernel():
    """Every weight and colour function of the blend is defined in ``mesh/kernel.py`` and nowhere else in the
    package (no second lumigraph, occlusion test, mask falloff or consensus), and the lumigraph's and the consensus'
    formulas appear in their kernel function only (the fused shader calls ``kernel.lumigraph``)."""
    modules = {p: code_of(p) for p in sorted((ROOT / "omnirecon").rglob("*.py")) if "node_modules" not in p.parts}
    where = {name: [p.relative_to(ROOT).as_posix() for p, fns in modules.items() if name in fns]
             for name in BLEND_FUNCTIONS}
    assert all(w == ["omnirecon/mesh/kernel.py"] for w in where.values()), where
    for name, fragment in FORMULAS.items():
        holders = [(p.relative_to(ROOT).as_posix(), fn) for p, fns in modules.items() for fn, code in fns.items()
                   if fragment in code]
        assert holders == [("omnirecon/mesh/kernel.py", name)], (name, holders)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A procedural scene with half its mesh (holes for the fill), a random omnirecon-tiny and 5 sources."""
    scene = load_scene(generate_scene(tmp_path_factory.mktemp("kernel"), 5, SynthOptions(resolution=48, views=8)))
    mesh = trimesh.load(scene.mesh_path, process=False, force="mesh")
    keep = np.asarray(mesh.triangles_center)[:, 0] < np.median(np.asarray(mesh.triangles_center)[:, 0])
    torch.manual_seed(0)
    return scene, trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False), build_model("omnirecon-tiny").eval()


def renderer_colours(model, mesh, sources, opts: MeshRenderOptions, target, fill: bool) -> tuple[torch.Tensor, ...]:
    """The renderer's colour at each shaded pixel of ``target``: ``(pixels # [P], rgb # [P, 3], odd # [P])`` (``odd``:
    no source has the point in front of it and inside its image, and it lies behind some source)."""
    with MeshRenderer(model, mesh, sources, opts) as r:
        shaded = r.weights(target, with_rgb=True, with_coords=not opts.fused, fill=fill)
        rgb = shaded.rgb if shaded.rgb is not None else r.blend(shaded, r._rgb)
        _, z, framed = r._frame_points(shaded.surface.points.T.to(r.dtype).contiguous())
    return shaded.surface.pixels, rgb.float(), ~framed.any(0) & (z <= 1e-6).any(0)


@pytest.mark.usefixtures("gl")
@pytest.mark.parametrize("blend, fill, masks", [("network", "far", False), ("network", "nearest", False),
                                                ("angle", "nearest", True), ("angle", "far", False)])
def test_tuner_and_renderer_colour_the_same_pixels_alike(setup, blend, fill, masks):
    """The pixels finetune scores and tunes on (its rasterized surface and fill, the occlusion test, the network's or
    the angle blend's weights, with an object capture's source masks) get the colours the real-time renderer gives the
    same pixels, from its fused shader and from its reference path; the tuner's colours carry gradients to the
    appearance branch and equal its scores without them."""
    scene, mesh, model = setup
    if masks:  # an object capture whose masks hold the scene (masks_hold_scene)
        scene = replace(scene, background=None, rig="object")
    sources = Sources.from_scene(scene, SOURCES)
    target = scene.cameras[0].to(dtype=torch.float32)
    px = rasterize_views(mesh, scene, [0], fill=True, sources=SOURCES, nearest_fill=fill == "nearest")[0]
    if blend == "angle":
        angle_blend([px], scene, SOURCES, 2)
    with torch.no_grad():
        feats = encode_maps(model, sources)
        scored = render_pixels(model, feats, px)  # [P, 3]
    opts = MeshRenderOptions(fill=fill, visibility=True, blend=blend, angle_sources=2, cull_back_faces=False,
                             source_masks=masks)
    for fused in (True, False):
        pixels, rgb, odd = renderer_colours(model, mesh, sources, replace(opts, fused=fused), target, fill=True)
        assert torch.equal(pixels, px.pixels)  # the same pixels, mesh first and then the fill's
        diff = (rgb - scored).abs().amax(-1)
        # a point no source frames blends every source uniformly in both, but the fused shader's projection of a point
        # behind a source, (K [R|t] p) / max(z, eps), may clamp to another border texel than Cameras.project's
        # (fx x / eps + cx): such fill pixels (1 of 2304 differs here) may differ where the renderer samples the colours
        # (the fused shader; the reference path's angle blend), not where model.shade does (its network blend)
        exact = ~odd if fused or blend == "angle" else torch.ones_like(odd)
        assert float(diff[exact].max()) < 1e-4, (fused, float(diff[exact].max()))
        assert float(exact.float().mean()) > 0.8 and float((diff > 1e-4).float().mean()) < 0.01
    if blend == "network":  # with gradients on: the same colours, and a gradient on the appearance branch
        rows = torch.arange(0, len(px.points), 7)
        rgb = point_colours(model, encode_maps(model, sources), px.points[rows], px.origin.expand(len(rows), 3),
                            px.visible[rows])
        assert torch.allclose(rgb.detach(), scored[rows], atol=1e-6)
        rgb.square().mean().backward()
        grads = [p.grad for p in model.appearance.parameters()]
        assert all(g is not None for g in grads) and any(float(g.abs().sum()) > 0 for g in grads)
        model.zero_grad(set_to_none=True)


def test_angle_blend_weights_are_the_lumigraph_of_the_k_nearest_seen_sources_times_the_masks():
    """``angle_blend_weights``: at a point with sources at 10, 20, 30 and 40 degrees (the 30-degree one unseen) and
    ``k = 2``, the 10- and 20-degree sources weigh ``(1 - a / 40) / a`` normalised (the next seen source, 40
    degrees, sets the falloff), the others 0; a mask factor of 0.5 on the nearest re-weights it; a point no source
    sees blends all uniformly."""
    deg = torch.tensor([10.0, 20.0, 30.0, 40.0])
    ang = torch.deg2rad(deg)
    centers = torch.stack([torch.sin(ang), torch.zeros(4), -torch.cos(ang)], 1) * 2  # sources around the point
    points, origin = torch.zeros(2, 3), torch.tensor([0.0, 0.0, -2.0])
    seen = torch.tensor([[True, True, False, True], [False, False, False, False]])
    w = kernel.angle_blend_weights(points, origin, centers, seen, 2)
    raw = (1 - ang[:2] / ang[3]) / ang[:2]
    assert torch.allclose(w[0], torch.cat([raw / raw.sum(), torch.zeros(2)]), atol=1e-5), w[0]
    assert torch.allclose(w[1], torch.full((4,), 0.25))
    factor = torch.tensor([[0.5, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]])
    masked = kernel.angle_blend_weights(points, origin, centers, seen, 2, factor)
    half = raw * torch.tensor([0.5, 1.0])
    assert torch.allclose(masked[0, :2], half / half.sum(), atol=1e-5)
