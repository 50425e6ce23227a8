import torch

from omnirecon.cameras import Cameras, look_at
from omnirecon.models.floor import PlaneSweep, PlaneSweepConfig
from omnirecon.rays import Sources


def test_plane_sweep_recovers_a_textured_plane():
    """Sources see a textured plane at z = 0 from 3 m: the sweep finds its depth and colour."""
    n, w, h = 5, 48, 40
    xs = torch.linspace(-0.5, 0.5, n)
    eye = torch.stack([xs, torch.zeros(n), torch.full((n,), -3.0)], -1)
    c2w = look_at(eye, eye + torch.tensor([0, 0, 1.0]), torch.tensor([0, -1.0, 0]))
    cams = Cameras(torch.full((n,), 40.0), torch.full((n,), 40.0), torch.full((n,), w / 2), torch.full((n,), h / 2), c2w, w, h)

    def texture(p):  # colour of the plane at world x, y
        x, y = p[..., 0], p[..., 1]  # incommensurate frequencies: no periodic false matches
        return torch.stack([0.5 + 0.25 * torch.sin(7 * x) + 0.2 * torch.sin(17.3 * x + 2 * y),
                            0.5 + 0.3 * torch.cos(5 * y) + 0.15 * torch.sin(11.1 * x),
                            0.5 + 0.25 * torch.sin(3 * x + 4 * y) + 0.2 * torch.cos(23.7 * x)], -1)

    o, d = cams.image_rays(normalize=False)  # z = 1 directions
    hit = o + d * (0.0 - o[..., 2:3])  # the plane z = 0, 3 m in front of cameras at z = -3
    images = texture(hit)  # [N, H, W, 3]
    src = [0, 1, 3, 4]
    model = PlaneSweep(PlaneSweepConfig(num_depths=81))
    feats = model.encode(Sources(images[src], cams[src], 2.0, 4.0))
    out = model.render_view(feats, cams[[2]])
    centre = (slice(8, -8), slice(8, -8))
    assert (out["depth"][centre] - 3.0).abs().median() < 0.03
    # bilinear resampling of the finest (3.5 px period) texture term costs ~0.02
    assert (out["rgb"][centre] - images[2][centre]).abs().mean() < 0.04


def test_rays_without_agreement_fall_back_to_the_source_mean():
    """A ray only one source sees gets that source's mean colour along it, not black."""
    n, w, h = 2, 16, 16
    eye = torch.tensor([[0.0, 0, -3], [40.0, 0, -3]])  # the second camera sees nothing the first does
    c2w = look_at(eye, eye + torch.tensor([0, 0, 1.0]), torch.tensor([0, -1.0, 0]))
    cams = Cameras(torch.full((n,), 16.0), torch.full((n,), 16.0), torch.full((n,), 8.0), torch.full((n,), 8.0), c2w, w, h)
    images = torch.full((1, h, w, 3), 0.7)
    model = PlaneSweep(PlaneSweepConfig(num_depths=16))
    out = model.render_view(model.encode(Sources(images, cams[[0]], 2.0, 4.0)), cams[[0]])
    assert not out["valid"].any()
    assert torch.allclose(out["rgb"], torch.full_like(out["rgb"], 0.7), atol=1e-5)
