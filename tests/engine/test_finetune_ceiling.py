"""The blend ceiling of `python -m bench finetune_ceiling`: the per-pixel best convex blend of the source colours."""

import torch

from bench.finetune_ceiling import best_blend, project_simplex


def test_simplex_projection_keeps_allowed_entries_on_the_simplex():
    torch.manual_seed(0)
    w, allowed = torch.randn(500, 4), torch.rand(500, 4) > 0.3
    p = project_simplex(w, allowed)
    rows = allowed.any(-1)
    assert (p >= 0).all() and (p[~allowed] == 0).all()
    assert torch.allclose(p[rows].sum(-1), torch.ones(int(rows.sum())), atol=1e-5)


def test_best_blend_matches_a_grid_search_and_never_loses_to_the_uniform_blend():
    torch.manual_seed(1)
    colours, target = torch.rand(200, 3, 3), torch.rand(200, 3)
    best = best_blend(colours, torch.ones(200, 3, dtype=torch.bool), target, iters=500)
    g = torch.stack(torch.meshgrid(torch.linspace(0, 1, 101), torch.linspace(0, 1, 101), indexing="ij"), -1).reshape(-1, 2)
    g = g[g.sum(-1) <= 1]
    w = torch.cat([g, 1 - g.sum(-1, keepdim=True)], -1)  # [G, 3] on the simplex
    grid = (torch.einsum("gk,pkc->pgc", w, colours) - target[:, None]).square().sum(-1).min(-1).values
    err = (best - target).square().sum(-1)
    assert (err <= grid + 1e-4).all()
    assert (err <= (colours.mean(1) - target).square().sum(-1) + 1e-6).all()
