"""Rays and the projector's gather: points along rays, rays of an image, samples laid out per point."""

import torch
import torch.nn.functional as F

from omnirecon.models.projector import gather, project, sample
from omnirecon.rays import Rays
from tests.models.test_gpnr import rig


def test_from_image_equals_per_pixel_rays():
    """Rays.from_image (the camera broadcast) equals Rays.from_pixels with one camera per pixel."""
    cam = rig(dtype=torch.float32)[[2]]
    uv = cam.pixel_centers().reshape(-1, 2)
    per_pixel = Rays.from_pixels(cam, torch.zeros(len(uv), dtype=torch.long), uv)
    rays = Rays.from_image(cam)
    assert len(rays) == cam.height * cam.width
    for name in ("origins", "directions", "up", "z_scale"):
        torch.testing.assert_close(getattr(rays, name), getattr(per_pixel, name), atol=1e-6, rtol=0, msg=name)
    assert rays.origins.stride(0) == 0  # a view of the camera centre, not R copies


def test_points_sit_at_their_z_depth():
    """Rays.points(z): the camera-frame z of each point is z, for per-ray depths and for shared ones."""
    cam = rig(dtype=torch.float64)[[1]]
    rays = Rays.from_image(cam)[::5]
    z = torch.linspace(2.0, 4.0, 7, dtype=torch.float64)
    for zz in (z, z.expand(len(rays), 7)):
        pts = rays.points(zz)  # [R, 7, 3]
        assert pts.shape == (len(rays), 7, 3)
        cam_z = (pts - cam.centers[0]) @ cam.forward[0]
        torch.testing.assert_close(cam_z, z.expand(len(rays), 7), atol=1e-9, rtol=0)
        torch.testing.assert_close((pts - rays.origins[:, None]).norm(dim=-1), rays.distances(zz), atol=1e-9, rtol=0)
        torch.testing.assert_close(rays.points(zz, unit_z=True), pts, atol=1e-12, rtol=0)  # the other rounding


def test_gather_lays_out_samples_per_point():
    """gather(maps, project(cams, points [R, S, 3])) is sample() reshaped to [R, S, V, C]; the mask is
    in_image as [R, S, V]."""
    torch.manual_seed(0)
    cams = rig(dtype=torch.float32)
    pts = torch.randn(6, 4, 3)
    maps = torch.rand(len(cams), 5, cams.height, cams.width)
    proj = project(cams, pts)
    out = gather(maps, proj, "border")
    flat = sample(maps, project(cams, pts.reshape(-1, 3)), "border")  # [V, C, R*S]
    assert out.shape == (6, 4, len(cams), 5)
    assert torch.equal(out, flat.reshape(len(cams), 5, 6, 4).permute(2, 3, 0, 1))
    assert torch.equal(proj.mask, proj.in_image.reshape(len(cams), 6, 4).permute(1, 2, 0))
    ref = F.grid_sample(maps, proj.grid, align_corners=False, padding_mode="border")[:, :, 0]
    assert torch.equal(flat, ref)


def test_gather_of_several_maps_concatenates_channels():
    """gather([a, b], paddings): the samples of each map with its padding, channels concatenated, laid out
    as a single map's samples (same strides: reductions over views round the same way)."""
    torch.manual_seed(1)
    cams = rig(dtype=torch.float32)
    proj = project(cams, torch.randn(5, 3, 3))
    a = torch.rand(len(cams), 3, cams.height, cams.width)
    b = torch.rand(len(cams), 4, cams.height, cams.width)
    both = gather([a, b], proj, ["border", "zeros"])
    assert torch.equal(both, torch.cat([gather(a, proj, "border"), gather(b, proj, "zeros")], -1))
    assert both.stride() == gather(torch.cat([a, b], 1), proj).stride()
