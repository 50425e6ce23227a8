"""Depth edges of a rendered view and the blur there (``omnirecon.render.edges``)."""

import torch

from omnirecon.render.edges import depth_edges, gaussian_blur, soften_edges


def test_depth_edges_are_steps_and_outlines_not_slanted_planes_nor_the_border():
    i, j = torch.meshgrid(torch.arange(12.0), torch.arange(16.0), indexing="ij")
    plane = 1 / (0.5 + 0.2 * j + 0.1 * i)  # [12, 16] a steep plane: inverse depth linear in the image
    assert not depth_edges(plane).any()
    step = torch.where(j < 8, torch.ones_like(j), torch.full_like(j, 1.5))  # a depth step between columns 7 and 8
    e = depth_edges(step)
    assert e[:, 7:9].all() and not e[:, :7].any() and not e[:, 9:].any()
    outline = torch.where((i - 6).abs() + (j - 8).abs() < 4, torch.ones_like(i), torch.zeros_like(i))  # 0: no surface
    e = depth_edges(outline)
    has = outline > 0
    near_off = torch.nn.functional.max_pool2d((~has).float()[None, None], 3, 1, 1)[0, 0] > 0  # an off pixel in 3x3
    assert torch.equal(e[has], near_off[has])  # the mesh's rim (its own depth is flat inside)
    near_on = torch.nn.functional.max_pool2d(has.float()[None, None], 3, 1, 1)[0, 0] > 0
    assert torch.equal(e[~has], near_on[~has]) and not e[0].any()  # and the pixels just off it


def test_soften_edges_blurs_only_the_edge_pixels():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(10, 14, 3, generator=g)
    depth = torch.ones(10, 14)
    depth[:, 7:] = 2.0
    out = soften_edges(img, depth, 0.7)
    edge = depth_edges(depth)
    assert torch.equal(out[~edge], img[~edge])
    assert torch.allclose(out[edge], gaussian_blur(img, 0.7)[edge]) and not torch.allclose(out[edge], img[edge])
    assert torch.equal(soften_edges(img, depth, 0.0), img)
    flat = torch.full((10, 14, 3), 0.3)
    assert torch.allclose(gaussian_blur(flat, 1.3), flat)  # weights sum to 1, border replicated


def test_the_cpu_fast_paths_equal_their_torch_twins(monkeypatch):
    """The OpenCV paths of the CPU (depth edges, blur, the in-place softening) against the torch code every other
    device runs, on random depths with holes and plateaus."""
    import numpy as np

    import omnirecon.render.edges as E

    rng = np.random.default_rng(0)
    cases = []
    for it in range(120):
        H, W = (int(n) for n in rng.integers(1, 30, 2))
        d = (rng.random((H, W)) * 2 + 0.5) * (rng.random((H, W)) < rng.random())
        if it % 3 == 0:  # near-planar steps
            d = np.where(rng.random((H, W)) < 0.9, 1.0, 1.0 + rng.random((H, W)) * 0.05)
        cases.append((torch.from_numpy(d).float(), torch.from_numpy(rng.random((H, W, 3))).float()))
    fast = [(E.depth_edges(d), E.gaussian_blur(img, 0.7), E.soften_edges(img, d, 0.7)) for d, img in cases]
    monkeypatch.setattr(E, "_host", lambda t: False)
    for (d, img), (edge, blur, soft) in zip(cases, fast):
        assert torch.equal(edge, E.depth_edges(d))
        assert torch.allclose(blur, E.gaussian_blur(img, 0.7), atol=1e-6)
        assert torch.allclose(soft, E.soften_edges(img, d, 0.7), atol=1e-6)
