"""Omni-Recon: shapes, subtraction attention against a slow loop, appearance/geometry decoupling,
source-permutation invariance, a one-batch overfit and the training CLI (small overrides, CPU)."""

import dataclasses
import json
from pathlib import Path

import pytest
import torch

from omnirecon.models.omnirecon import PRESETS, OmniRecon, OmniReconConfig, SubtractionAttention, nearest_sources
from omnirecon.rays import Rays, Sources
from tests.models.test_gpnr import rig

SMALL = dict(coarse_samples=8, fine_samples=4, cnn_channels=(4, 8, 8, 8), feature_dim=8, pyramid_channels=(4, 4, 4),
             volume_resolution=8, heads=2, ffn_mult=2, pe_freqs=4)


def small_cfg(**kw) -> OmniReconConfig:
    return OmniReconConfig(**{**PRESETS["omnirecon-tiny"].__dict__, **SMALL, **kw})


def setup(cfg: OmniReconConfig, seed: int = 0):
    """A double-precision model in eval mode, 4 sources of random images, the middle camera as target."""
    torch.manual_seed(seed)
    model = OmniRecon(cfg).double().eval()
    cams = rig()
    images = torch.rand(len(cams) - 1, cams.height, cams.width, 3, dtype=torch.float64)
    bounds = torch.tensor([[-1.0, -1.0, -0.5], [1.0, 1.0, 0.5]], dtype=torch.float64)
    srcs = cams[[0, 1, 3, 4]]
    rays = Rays.from_pixels(cams[[2]], torch.zeros(30, dtype=torch.long),
                            torch.rand(30, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 20)
    return model, Sources(images, srcs, 2.0, 4.0, "object", bounds), rays, cams[[2]]


def test_outputs_and_shapes():
    model, src, rays, target = setup(small_cfg())
    feats = model.encode(src)
    assert feats.maps.shape == (4, 8, 5, 6) and feats.volume.shape == (1, 8, 8, 8, 8)
    out = model.render_rays(feats, rays, return_samples=True)
    R, S, K = 30, 12, 4
    for key, shape in [("rgb", (R, 3)), ("rgb_coarse", (R, 3)), ("depth", (R,)), ("depth_coarse", (R,)),
                       ("weights", (R, S)), ("z", (R, S)), ("sdf", (R, S)), ("blend", (R, K)), ("acc", (R,)),
                       ("valid", (R,)), ("blend_samples", (R, S, K))]:
        assert out[key].shape == shape, key
    w = out["weights"]
    assert (w >= 0).all() and (w.sum(-1) <= 1 + 1e-5).all()
    assert (out["z"].diff(dim=-1) >= 0).all() and (out["z"] >= 2 - 1e-9).all() and (out["z"] <= 4 + 1e-9).all()
    assert torch.allclose(out["blend_samples"].sum(-1), torch.ones(R, S, dtype=torch.float64))
    assert torch.allclose(out["blend"].sum(-1), out["acc"])  # per-ray blend = omega composited with w
    assert torch.allclose(out["blend"], (w[..., None] * out["blend_samples"]).sum(1))
    assert (out["rgb"] >= 0).all() and (out["rgb"] <= out["acc"][:, None] + 1e-9).all()  # convex blends
    assert torch.allclose(out["depth"], (w * out["z"]).sum(-1))
    # training mode: jitter and importance sampling draw random samples, still sorted in [near, far]
    outj = model.train().render_rays(feats, rays, jitter=True)
    assert (outj["z"].diff(dim=-1) >= 0).all() and (outj["z"] >= 2 - 1e-9).all() and (outj["z"] <= 4 + 1e-9).all()
    img = model.eval().render_view(feats, target, chunk=100)
    assert img["rgb"].shape == (20, 24, 3) and img["depth"].shape == (20, 24) and img["blend"].shape == (20, 24, 4)
    coarse_only = OmniRecon(small_cfg(fine_samples=0)).double().eval()
    out0 = coarse_only.render_rays(coarse_only.encode(src), rays)
    assert out0["weights"].shape == (R, 8) and out0["rgb_coarse"] is out0["rgb"]


@pytest.mark.parametrize("leftover", ["far", "renormalize"])
def test_leftover_transmittance(leftover):
    """``leftover`` only moves the transmittance left after the last sample: with ``far`` the last sample
    takes it, with ``renormalize`` every weight is scaled by 1 / acc; either way each ray's opacity is 1."""
    # renormalize: the coarse pass only, since importance sampling adds 1e-5 to the (rescaled) coarse weights
    model, src, rays, _ = setup(small_cfg(leftover="black", fine_samples=4 if leftover == "far" else 0))
    feats = model.encode(src)
    black = model.render_rays(feats, rays)
    assert (black["acc"] < 0.99).any()  # random weights leave rays that find no surface
    model.cfg = dataclasses.replace(model.cfg, leftover=leftover)  # the same weights, the other rule
    out = model.render_rays(feats, rays)
    ones = torch.ones(30, dtype=torch.float64)
    assert torch.allclose(out["acc"], ones) and torch.allclose(out["blend"].sum(-1), ones)
    wb, w = black["weights"], out["weights"]
    if leftover == "far":  # importance samples ignore the end samples' weights: the same z in both passes
        assert torch.equal(out["z"], black["z"])
        assert torch.allclose(w[:, :-1], wb[:, :-1]) and torch.allclose(w[:, -1], 1 - wb[:, :-1].sum(-1))
    else:
        assert torch.allclose(w, wb / wb.sum(-1, keepdim=True))
        assert torch.allclose(out["rgb"], black["rgb"] / black["acc"][:, None])
        assert torch.allclose(out["depth"], black["depth"] / black["acc"])


def test_backdrop_gives_far_colours_and_black_geometry():
    """``leftover="backdrop"``: rgb equals ``far``'s; depth, acc, weights and blend equal ``black``'s (meshing reads
    acc as confidence, so empty rays add no far-plane surface)."""
    model, src, rays, _ = setup(small_cfg(leftover="black", fine_samples=4))
    feats = model.encode(src)
    out = {}
    for rule in ("black", "far", "backdrop"):
        model.cfg = dataclasses.replace(model.cfg, leftover=rule)
        out[rule] = model.render_rays(feats, rays)
    assert (out["black"]["acc"] < 0.99).any()
    assert torch.allclose(out["backdrop"]["rgb"], out["far"]["rgb"], atol=1e-12)
    assert not torch.allclose(out["backdrop"]["rgb"], out["black"]["rgb"])
    for key in ("depth", "acc", "weights", "blend", "z"):
        assert torch.equal(out["backdrop"][key], out["black"][key]), key


def test_batchnorm_normalises_each_scene_alike_in_train_and_eval():
    """``bn_running_stats=False``: eval mode uses the scene's own statistics, as training does."""
    model, src, rays, _ = setup(small_cfg())
    a = model.eval().render_rays(model.encode(src), rays)
    b = model.train().render_rays(model.encode(src), rays)
    assert torch.allclose(a["rgb"], b["rgb"], atol=1e-12) and torch.allclose(a["depth"], b["depth"], atol=1e-12)
    assert not any("running" in k for k in model.state_dict())
    ref = OmniRecon(small_cfg(bn_running_stats=True)).double()
    assert any("running_mean" in k for k in ref.state_dict())
    with pytest.raises(ValueError, match="volume_resolution"):
        OmniRecon(small_cfg(volume_resolution=4))


def test_volume_box_modes():
    model, src, _, _ = setup(small_cfg(volume_margin=0.1))
    box = model.encode(src).box
    assert torch.allclose(box, torch.tensor([[-1.1, -1.1, -0.6], [1.1, 1.1, 0.6]], dtype=torch.float64))
    unit = OmniRecon(small_cfg(volume_bounds="unit")).double().eval()
    assert torch.equal(unit.encode(src).box, torch.tensor([[-1.0] * 3, [1.0] * 3], dtype=torch.float64))
    src.bounds = None  # no content box: the unit cube
    assert torch.equal(model.encode(src).box, torch.tensor([[-1.0] * 3, [1.0] * 3], dtype=torch.float64))


def test_forward_box_holds_the_source_cameras():
    """On a forward-facing rig the ``scene`` box grows to the source cameras (``forward_box="cameras"``, the
    default); ``content`` keeps the content box; object rigs keep it either way."""
    model, src, _, _ = setup(small_cfg(volume_margin=0.0))
    centres = src.cameras.centers
    assert not ((centres >= src.bounds[0]) & (centres <= src.bounds[1])).all()  # the rig's cameras sit outside
    assert torch.equal(model.encode(src).box, src.bounds)  # object rig: the content box
    src.rig = "forward"
    box = model.encode(src).box
    assert ((centres >= box[0] - 1e-12) & (centres <= box[1] + 1e-12)).all()
    assert torch.equal(box, torch.stack([torch.minimum(src.bounds[0], centres.amin(0)),
                                         torch.maximum(src.bounds[1], centres.amax(0))]))
    content = OmniRecon(small_cfg(volume_margin=0.0, forward_box="content")).double().eval()
    assert torch.equal(content.encode(src).box, src.bounds)


def test_lattice_and_volume_sampling_agree():
    """A volume holding its voxel centres' coordinates, sampled trilinearly, returns the query points."""
    from omnirecon.models.omnirecon import OmniReconFeatures, lattice

    model, src, _, _ = setup(small_cfg())
    box = torch.tensor([[-1.0, -0.5, 0.0], [1.0, 0.5, 2.0]], dtype=torch.float64)
    res = 6
    coords = lattice(box, res).T.reshape(1, 3, res, res, res)  # channels x, y, z  [1, 3, Z, Y, X]
    feats = OmniReconFeatures(src, torch.zeros(4, 1, 1, 1, dtype=torch.float64), coords, box)
    cell = (box[1] - box[0]) / res
    pts = box[0] + cell / 2 + torch.rand(2, 5, 3, dtype=torch.float64) * (box[1] - box[0] - cell)  # inside the centres
    assert torch.allclose(model.volume_features(feats, pts), pts, atol=1e-12)
    outside = model.volume_features(feats, torch.tensor([[[3.0, 0.0, 1.0]]], dtype=torch.float64))
    assert torch.equal(outside, torch.zeros(1, 1, 3, dtype=torch.float64))  # zero padding


def test_mean_var_volume_masks_views():
    """Mean and variance over the views that see a voxel: three copies of one camera with the same map
    give that map's sample and zero variance; voxels no view sees are zero."""
    from omnirecon.models.omnirecon import lattice, mean_var_volume

    cams = rig()[[0, 0, 0]]
    maps = torch.rand(1, 2, 5, 6, dtype=torch.float64).expand(3, -1, -1, -1)
    pts = lattice(torch.tensor([[-3.0] * 3, [3.0] * 3], dtype=torch.float64), 8)
    vol = mean_var_volume(maps, cams, pts, 8).reshape(4, -1)  # mean (2) | variance (2)  [4, P]
    one = mean_var_volume(maps[:1], cams[[0]], pts, 8).reshape(4, -1)
    seen = cams.project(pts).in_image[0]
    assert 0 < seen.sum() < len(pts)
    assert torch.allclose(vol, one, atol=1e-12) and torch.allclose(vol[2:], torch.zeros_like(vol[2:]), atol=1e-12)
    assert (vol[:, ~seen] == 0).all() and (vol[:2, seen] != 0).any()


def _mlp(seq, x):
    """``Linear -> ReLU -> Linear`` by hand."""
    h = torch.clamp_min(seq[0].weight @ x + seq[0].bias, 0)
    return seq[2].weight @ h + seq[2].bias


def slow_subtraction_attention(att: SubtractionAttention, q, views, dirs, mask):
    """The equations of §3.3, one sample and one view at a time."""
    out = []
    for n in range(q.shape[0]):
        qp = att.q.weight @ q[n]
        logits, values = [], []
        for i in range(views.shape[1]):
            kp = att.k.weight @ views[n, i]
            p = _mlp(att.pos, dirs[n, i])
            a = _mlp(att.score, kp - qp + p)
            logits.append(a if mask[n, i] else torch.full_like(a, -1e9))
            values.append(att.v.weight @ kp + p)
        L = torch.stack(logits)  # [K, D]: a softmax over views for every channel
        e = torch.exp(L - L.max(0).values)
        alpha = e / e.sum(0)
        o = sum(alpha[i] * values[i] for i in range(len(values)))
        out.append(att.out.weight @ o + att.out.bias)
    return torch.stack(out)


def test_subtraction_attention_matches_slow_loop():
    torch.manual_seed(0)
    att = SubtractionAttention(16, dropout=0.0).double()
    N, K = 7, 4
    q, views = torch.randn(N, 16, dtype=torch.float64), torch.randn(N, K, 16, dtype=torch.float64)
    dirs = torch.randn(N, K, 4, dtype=torch.float64)
    mask = torch.rand(N, K) > 0.3  # row 4 is all False: a sample no view sees (uniform weights)
    mask[0] = torch.tensor([True, False, True, True])
    fast = att(q, views, dirs, mask)
    assert torch.allclose(fast, slow_subtraction_attention(att, q, views, dirs, mask), atol=1e-10)
    # leading dimensions [R, S] are batch dimensions
    fast2 = att(q.reshape(1, N, 16), views.reshape(1, N, K, 16), dirs.reshape(1, N, K, 4), mask.reshape(1, N, K))
    assert torch.allclose(fast2[0], fast, atol=1e-12)
    # masked views do not matter, whatever their tokens
    views2 = torch.where(mask[..., None], views, torch.randn_like(views) * 10)
    seen = mask.any(-1)
    assert torch.allclose(att(q, views2, dirs, mask)[seen], fast[seen], atol=1e-10)


def _grads_zero(module) -> bool:
    return all(p.grad is None or not p.grad.any() for p in module.parameters())


def test_appearance_branch_is_decoupled_from_geometry():
    """omega depends only on the 2-D feature F_i and the directions: no gradient reaches the volume,
    the pyramid maps, the geometry branch or the SDF sharpness; the shader path gives the same omega."""
    model, src, rays, _ = setup(small_cfg())
    feats = model.encode(src)
    feats.volume.retain_grad()
    out = model.render_rays(feats, rays, return_samples=True)
    omega = out["blend_samples"]  # [R, S, K]
    (omega * torch.rand_like(omega)).sum().backward()
    assert feats.volume.grad is None or not feats.volume.grad.any()
    for part in (model.volume, model.geometry, model.encoder.pyramid):
        assert _grads_zero(part)
    assert model.deviation.grad is None or model.deviation.grad == 0
    assert not _grads_zero(model.appearance) and not _grads_zero(model.encoder.out)
    # the shader (§7) computes omega from surface points alone, no geometry branch involved
    t = out["z"] / rays.z_scale[:, None]
    pts = rays.origins[:, None] + rays.directions[:, None] * t[..., None]  # [R, S, 3]
    shaded = model.shade(feats, pts.reshape(-1, 3).detach(), rays.origins.repeat_interleave(t.shape[1], 0))
    assert torch.allclose(shaded["blend"], omega.reshape(-1, 4).detach(), atol=1e-10)
    # positive control: the colour loss does reach the geometry branch and the volume
    model.zero_grad(set_to_none=True)
    out = model.render_rays(model.encode(src), rays)
    out["rgb"].sum().backward()
    assert not _grads_zero(model.geometry) and not _grads_zero(model.volume) and model.deviation.grad != 0


def test_invariant_to_source_permutation():
    model, src, rays, _ = setup(small_cfg())
    a = model.render_rays(model.encode(src), rays)
    perm = torch.tensor([2, 0, 3, 1])
    permuted = Sources(src.images[perm], src.cameras[perm], src.near, src.far, src.rig, src.bounds)
    b = model.render_rays(model.encode(permuted), rays)
    for k in ("rgb", "rgb_coarse", "depth", "sdf", "weights", "valid"):
        assert torch.allclose(a[k].double(), b[k].double(), atol=1e-9), k
    assert torch.allclose(a["blend"][:, perm], b["blend"], atol=1e-9)


def test_paper_preset_sizes():
    cfg = PRESETS["omnirecon-paper"]
    sizes = (cfg.dim, cfg.volume_dim, cfg.volume_resolution, cfg.coarse_samples, cfg.fine_samples)
    assert sizes == (64, 32, 144, 64, 64)
    model = OmniRecon(cfg)
    count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    assert count(model.appearance) == 1777  # "about 1.8 k parameters" (§4)
    assert 1.2e6 < count(model) < 1.3e6  # "about 1.24 M" (§3.2)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    from omnirecon.data.synth import SynthOptions, generate_scene

    return generate_scene(tmp_path_factory.mktemp("scenes"), 0, SynthOptions(views=10, resolution=32, max_objects=3))


def test_overfits_one_batch(scene):
    """40 Adam steps on one batch (procedural seed 0, 32 px, 128 rays, 4 sources) cut the colour MSE (both
    passes) and the L1 depth (both passes), first 5 steps vs last 5, by >= 2x. Measured: 3.2x and 3.0x."""
    from omnirecon.data import load_scene
    from omnirecon.data.bank import draw_batch, prepare
    from omnirecon.engine.losses import depth_loss, masked_mse
    from omnirecon.models.registry import build_model

    batch = draw_batch(prepare(load_scene(scene), "s"), 4, 8, 128, torch.Generator().manual_seed(0), 0.5)
    assert batch.depth is not None and (batch.depth > 0).float().mean() > 0.5
    torch.manual_seed(0)
    model = build_model("omnirecon-tiny", {"volume_resolution": 16, "coarse_samples": 16, "fine_samples": 8})
    opt = torch.optim.Adam(model.parameters(), 3e-3)
    rows = []
    for _ in range(40):
        out = model.render_rays(model.encode(batch.sources), batch.rays, jitter=True)
        valid = out["valid"].float()
        colour = masked_mse(out["rgb"], batch.rgb, valid) + masked_mse(out["rgb_coarse"], batch.rgb, valid)
        depth = depth_loss(out, batch.depth, valid, batch.sources.near, batch.sources.far)
        opt.zero_grad()
        (colour + depth).backward()
        opt.step()
        rows.append((float(colour.detach()), float(depth.detach())))
    first = [sum(r[i] for r in rows[:5]) / 5 for i in (0, 1)]
    last = [sum(r[i] for r in rows[-5:]) / 5 for i in (0, 1)]
    print(f"colour {first[0]:.4f} -> {last[0]:.4f} ({first[0] / last[0]:.2f}x), "
          f"depth {first[1]:.4f} -> {last[1]:.4f} ({first[1] / last[1]:.2f}x)")
    assert first[0] / last[0] >= 2.0 and first[1] / last[1] >= 2.0


def test_train_cli(tmp_path, scene):
    """``omnirecon train --model omnirecon-tiny`` runs, logs and resolves the family defaults (depth weight 0.1)."""
    from omnirecon.cli import main
    from omnirecon.engine.checkpoint import load_checkpoint

    run = tmp_path / "run"
    args = ["train", "--model", "omnirecon-tiny", "--model-overrides", "volume_resolution=8", "coarse_samples=8",
            "fine_samples=4", "--data", str(scene), "--resolution", "32", "--steps", "2", "--rays", "32",
            "--log-every", "1", "--val-every", "0", "--ckpt-every", "0", "--out", str(run), "--threads", "1",
            "--no-progress"]
    assert main(args) == 0
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["resolved"]["depth_weight"] == 0.1 and cfg["resolved"]["rays"] == 32
    assert cfg["model_config"]["volume_resolution"] == 8
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2] and all(r["loss"] > 0 for r in rows)
    model = load_checkpoint(run / "checkpoints" / "final")[0]
    assert isinstance(model, OmniRecon) and model.cfg.fine_samples == 4
    bad = [str(tmp_path / "bad") if a == str(run) else a for a in args]
    assert main([*bad, "--depth-weight", "-1"]) == 2



def test_render_views_renders_from_the_nearest_sources_only():
    """``render_views = n``: ``render_view`` from more than n sources gives exactly the image of the n nearest ones
    (zero ``blend`` for the others); with n sources or fewer, or no option, every source is used."""
    model, src, _, target = setup(small_cfg())
    feats = model.encode(src)
    full = model.render_view(feats, target, chunk=200)
    keep = [1, 2]  # the sources (cams 1 and 3) either side of the target (cam 2)
    near = Sources(src.images[keep], src.cameras[keep], src.near, src.far, src.rig, src.bounds)
    pair = model.render_view(model.encode(near), target, chunk=200)
    model.cfg.render_views = 2
    two = model.render_view(feats, target, chunk=200)
    model.cfg.render_views = 4
    four = model.render_view(feats, target, chunk=200)
    model.cfg.render_views = None
    assert torch.equal(four["rgb"], full["rgb"])
    assert torch.allclose(two["rgb"], pair["rgb"], atol=1e-12) and not torch.allclose(two["rgb"], full["rgb"])
    assert two["blend"].shape == full["blend"].shape  # one channel per given source
    assert torch.allclose(two["blend"][..., keep], pair["blend"]) and (two["blend"][..., [0, 3]] == 0).all()
    forward = Sources(src.images, src.cameras, src.near, src.far, "forward", src.bounds)
    assert sorted(nearest_sources(forward, target, 2).tolist()) == keep  # by distance between centres too


def test_encoder_appearance_alone_and_checkpointed():
    """``FPNEncoder.appearance``: the appearance feature of ``forward`` bit for bit, and with ``checkpoint`` the same
    feature and the same gradients (finetune's tuned encoder on many large sources keeps only segment outputs)."""
    torch.manual_seed(0)
    enc = OmniRecon(small_cfg()).encoder.train()
    x = torch.rand(3, 3, 40, 36)
    full = enc(x)[0]
    grads = []
    for ckpt in (False, True):
        enc.zero_grad()
        maps = enc.appearance(x, checkpoint=ckpt)
        assert torch.equal(maps, full)
        (maps * torch.linspace(-1, 1, maps.numel()).reshape(maps.shape)).sum().backward()
        grads.append([p.grad.clone() for p in enc.parameters() if p.grad is not None])
    with torch.no_grad():
        assert torch.equal(enc.appearance(x, checkpoint=True), full)
    assert len(grads[0]) == len(grads[1]) > 10
    assert all(torch.allclose(a, b, rtol=1e-5, atol=1e-7) for a, b in zip(*grads))
