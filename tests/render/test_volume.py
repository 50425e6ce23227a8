import torch

from omnirecon.render.volume import (
    alpha_from_density,
    alpha_from_sdf,
    composite,
    sample_along_rays,
    sample_intervals,
    sample_pdf,
    weights_from_alpha,
)


def test_samples_span_range_and_inverse_depth():
    near, far = torch.tensor([1.0, 2.0]), torch.tensor([5.0, 10.0])
    t = sample_along_rays(near, far, 9)
    assert torch.allclose(t[:, 0], near) and torch.allclose(t[:, -1], far)
    ti = sample_along_rays(near, far, 9, inverse_depth=True)
    assert torch.allclose(1 / ti, torch.stack([torch.linspace(1 / a, 1 / b, 9) for a, b in zip(near, far)]))
    tj = sample_along_rays(near, far, 9, jitter=True, generator=torch.Generator().manual_seed(0))
    assert (tj.diff(dim=1) >= 0).all() and (tj >= near[:, None]).all() and (tj <= far[:, None]).all()


def test_weights_of_an_opaque_wall():
    t = torch.linspace(0, 1, 11).expand(3, 11)
    sigma = torch.zeros(3, 11)
    sigma[:, 6:] = 1e4  # wall from t = 0.6
    w, trans = weights_from_alpha(alpha_from_density(sigma, t))
    assert torch.allclose(w.sum(-1), torch.ones(3), atol=1e-4)
    assert (w.argmax(-1) == 6).all()
    assert torch.allclose(composite(w, t[..., None])[:, 0], torch.full((3,), 0.6), atol=1e-3)
    assert (trans[:, :7] > 0.999).all()


def test_sample_pdf_concentrates_on_heavy_bin():
    bins = torch.linspace(0, 1, 11).expand(2, 11)
    weights = torch.zeros(2, 10)
    weights[:, 3] = 1
    s = sample_pdf(bins, weights, 64)
    assert ((s >= 0.3) & (s <= 0.4)).float().mean() > 0.9
    s2 = sample_pdf(bins, weights, 64, deterministic=False, generator=torch.Generator().manual_seed(0))
    assert ((s2 >= 0.3) & (s2 <= 0.4)).float().mean() > 0.9


def test_sample_intervals_average_neighbouring_gaps():
    t = torch.tensor([[0.0, 1.0, 3.0, 6.0]])
    assert torch.allclose(sample_intervals(t), torch.tensor([[1.0, 1.5, 2.5, 3.0]]))


def test_sdf_alpha_of_a_plane():
    """SRDF ``t0 - t`` of a plane at ray distance ``t0``: weights sum to at most 1, peak at the sample
    nearest the plane, and the expected distance is the plane's; a ray that misses gets (almost) none."""
    t0 = torch.tensor([1.0, 0.5, 0.8, 1.31, 1.7])[:, None]
    uniform = torch.linspace(0, 2, 97).expand(5, 97)
    jittered = torch.sort(torch.rand(5, 97, generator=torch.Generator().manual_seed(0)) * 2, dim=-1).values
    for sharpness in (50.0, 400.0):
        for t in (uniform, jittered):
            w, _ = weights_from_alpha(alpha_from_sdf(t0 - t, t, sharpness), eps=1e-7)
            assert (w >= 0).all() and (w.sum(-1) <= 1 + 1e-5).all() and (w.sum(-1) > 0.99).all()
            assert torch.allclose((w * t).sum(-1), t0[:, 0], atol=0.03)
        w, _ = weights_from_alpha(alpha_from_sdf(t0 - uniform, uniform, sharpness), eps=1e-7)
        assert torch.equal(w.argmax(-1), (uniform - t0).abs().argmin(-1))
    # sharper = more concentrated around the plane
    spread = [(weights_from_alpha(alpha_from_sdf(t0 - uniform, uniform, s))[0] * (uniform - t0).abs()).sum(-1).mean()
              for s in (20.0, 400.0)]
    assert spread[1] < spread[0] / 5
    miss, _ = weights_from_alpha(alpha_from_sdf(torch.full_like(uniform, 5.0), uniform, 50.0))  # surface beyond the ray
    assert (miss.sum(-1) < 1e-2).all()
