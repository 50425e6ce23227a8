"""Each fast path of omnirecon.models.fast against its reference twin (plain fp32 eager, in
omnirecon.models.reference), within the tolerance stated here; training paths in forward and in gradients.
The output-changing options of two-pass models (fine_pass, surface_samples) are tested in test_passes.py."""

import pytest
import torch

from omnirecon.models import fast
from omnirecon.models.gpnr import GPNR
from omnirecon.models.ibrnet import IBRNet
from omnirecon.models.omnirecon import PRESETS as OMNI_PRESETS
from omnirecon.models.omnirecon import OmniRecon, OmniReconConfig
from omnirecon.rays import Sources
from tests.models.test_gpnr import rig
from tests.models.test_gpnr import small_cfg as gpnr_cfg
from tests.models.test_ibrnet import tiny as ibrnet_cfg


def omni_cfg(**kw):
    cfg = dict(OMNI_PRESETS["omnirecon-tiny"].__dict__)
    cfg.update(coarse_samples=12, fine_samples=6, cnn_channels=(4, 8, 8, 8), feature_dim=8,
               pyramid_channels=(4, 4, 4), volume_resolution=8)
    cfg.update(kw)
    return OmniReconConfig(**cfg)


MODELS = {"ibrnet": lambda: IBRNet(ibrnet_cfg()), "gpnr": lambda: GPNR(gpnr_cfg()),
          "omnirecon": lambda: OmniRecon(omni_cfg())}


def scene(seed=0):
    torch.manual_seed(seed)
    cams = rig(dtype=torch.float32)
    images = torch.rand(4, cams.height, cams.width, 3)
    bounds = torch.tensor([[-1.0] * 3, [1.0] * 3])
    return Sources(images, cams[[0, 1, 3, 4]], 2.0, 4.0, "object", bounds), cams[[2]]


def render(model, src, target, chunk=100, **switches):
    with fast.switches(**switches):
        with torch.no_grad():
            feats = model.encode(src)
        return model.render_view(feats, target, chunk=chunk)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_render_workers_give_the_serial_image_bit_for_bit(name):
    """Batches rendered on 2 threads side by side (``render_workers``), with and without per-ray sample depths
    (surface-guided rendering hands each batch its own rows): every output equal to one batch at a time, torch's
    thread count restored, and no graph recorded in the workers (inference mode holds in them)."""
    torch.manual_seed(0)
    model = MODELS[name]().eval()
    src, target = scene()
    rays = target.height * target.width
    depths = torch.linspace(2.2, 3.8, 5).expand(rays, 5) + torch.rand(rays, 1) * 0.1  # [R, 5], rows differ
    threads = torch.get_num_threads()
    outs = {}
    for workers in (1, 2):
        with fast.switches(render_batch=16, render_workers=workers), torch.no_grad():
            feats = model.encode(src)
            outs[workers] = (model.render_view(feats, target), model.render_view(feats, target, depths=depths))
        assert torch.get_num_threads() == threads
    for serial, parallel in zip(outs[1], outs[2]):
        assert set(serial) == set(parallel)
        for k in serial:
            assert torch.equal(serial[k], parallel[k]), k
            assert not parallel[k].requires_grad, k
    assert fast.render_workers(torch.device("cpu")) == (torch.get_num_threads() if not fast.FAST.compile else 1)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_render_view_fast_paths_equal_reference(name):
    """inference_mode + small render batches + preallocated outputs: the same image as the reference
    (list of chunks, no_grad) to 1e-5 (batching changes only the summation order of matmuls)."""
    torch.manual_seed(0)
    model = MODELS[name]().eval()
    src, target = scene()
    with fast.reference():
        ref = render(model, src, target)
    out = render(model, src, target, inference_mode=True, render_batch=32, preallocate=True, sdpa_attention=True,
                 inplace_elu=True)
    assert set(out) == set(ref)
    for k in ref:
        assert out[k].shape == ref[k].shape and out[k].dtype == ref[k].dtype, k
        if ref[k].is_floating_point():
            torch.testing.assert_close(out[k], ref[k], atol=1e-5, rtol=1e-5, msg=k)
        else:
            assert torch.equal(out[k], ref[k]), k
    assert not out["rgb"].requires_grad


@pytest.mark.parametrize("name", sorted(MODELS))
def test_bf16_render_within_tolerance(name):
    """bf16 autocast rendering: outputs keep fp32 and the colour stays within 35 dB PSNR of the fp32
    reference (bench/fast_paths.py measures the cost on a trained model and a held-out scene)."""
    torch.manual_seed(0)
    model = MODELS[name]().eval()
    src, target = scene()
    with fast.reference():
        ref = render(model, src, target)
    out = render(model, src, target, bf16_render=True)
    assert out["rgb"].dtype == torch.float32
    mse = (out["rgb"] - ref["rgb"]).square().mean().clamp_min(1e-12)
    assert -10 * torch.log10(mse) > 35, float(mse)


def _train_outputs(model, src, rays, **switches):
    """Loss of one training forward (jittered samples, fixed seed) and the gradients of every parameter."""
    model.zero_grad(set_to_none=True)
    with fast.switches(**switches):
        torch.manual_seed(3)
        out = model.render_rays(model.encode(src), rays, jitter=True)
        loss = out["rgb"].square().mean() + out["rgb_coarse"].square().mean() + out["depth"].mean()
        loss.backward()
    grads = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    return out, grads


@pytest.mark.parametrize("switches", [{"split_linear": True}, {"sdpa_attention": True, "inplace_elu": True}],
                         ids=["split_linear", "sdpa_attention+inplace_elu"])
def test_ibrnet_exact_paths_forward_and_gradients(switches):
    """IBRNet's exact fast paths in training, each against its reference twin: the MLPs' first layer split by
    input block (reference: concatenation), the ray transformer through scaled_dot_product_attention with a
    boolean key mask (reference: nn.MultiheadAttention) with the ELUs in place. Forward to 1e-5, gradients of
    every parameter to 1e-4 relative (float rounding)."""
    from omnirecon.rays import Rays

    torch.manual_seed(0)
    model = IBRNet(ibrnet_cfg()).train()
    src, target = scene()
    rays = Rays.from_image(target)[::3]
    with fast.reference():
        ref, ref_g = _train_outputs(model, src, rays)
        out, out_g = _train_outputs(model, src, rays, **switches)
    for k in ("rgb", "rgb_coarse", "depth"):
        torch.testing.assert_close(out[k], ref[k], atol=1e-5, rtol=1e-5)
    assert set(out_g) == set(ref_g) and len(ref_g) > 10 and any("attn" in n for n in ref_g)
    for n in ref_g:
        torch.testing.assert_close(out_g[n], ref_g[n], atol=1e-6, rtol=1e-4, msg=n)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_compiled_networks_equal_reference(name, monkeypatch):
    """torch.compile of the per-sample networks inside render_view: one graph per network (no graph break), and the
    same image as the reference to 1e-4, the padded last batch included. Compiled with dynamo's ``aot_eager``
    backend: what is ours (the capture, the batching, the padding) is checked here in seconds; inductor's C++ kernels
    cost 70-200 CPU-s to build cold on 2 cores, so their numerics are measured by ``python -m bench fast_paths
    --compile`` and their persistent cache by ``python -m bench compile_cache``."""
    import functools

    from torch._dynamo.utils import counters

    monkeypatch.setattr(torch, "compile", functools.partial(torch.compile, backend="aot_eager"))
    torch._dynamo.reset()
    counters.clear()
    torch.manual_seed(0)
    model = MODELS[name]().eval()
    src, target = scene()
    with fast.reference():
        ref = render(model, src, target)
    out = render(model, src, target, compile=True, render_batch=64)  # 480 rays: 7 full batches + 1 padded
    assert {"rgb", "depth"} <= set(ref) and set(out) == set(ref)
    for k in ref:
        torch.testing.assert_close(out[k], ref[k], atol=1e-4, rtol=1e-4, msg=k)
    assert counters["stats"]["unique_graphs"] >= 1 and not counters["graph_break"], dict(counters["graph_break"])
    torch._dynamo.reset()


@pytest.mark.parametrize("name", sorted(MODELS))
def test_train_batch_forward_and_gradients(name):
    """A training forward in sub-batches of rays (one graph): the outputs to 1e-5 and the gradients of
    every parameter to 1e-4 relative of the one-call reference (deterministic samples: the jittered ones
    draw their random numbers in another order)."""
    from omnirecon.rays import Rays

    torch.manual_seed(0)
    model = MODELS[name]().train()
    src, target = scene()
    rays = Rays.from_image(target)[::4]  # 120 rays

    def run(**sw):
        model.zero_grad(set_to_none=True)
        with fast.switches(**sw):
            out = model.render_rays_batched(model.encode(src), rays)
            loss = out["rgb"].square().mean() + out["depth"].mean() + out.get("rgb_aux", out["rgb"]).mean()
            loss.backward()
        return out, {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}

    with fast.reference():
        ref, ref_g = run()
        out, out_g = run(train_batch=32)  # 3 full sub-batches and one of 24
    for k in ("rgb", "depth"):
        torch.testing.assert_close(out[k], ref[k], atol=1e-5, rtol=1e-5, msg=k)
    assert set(out_g) == set(ref_g) and ref_g
    for n in ref_g:
        torch.testing.assert_close(out_g[n], ref_g[n], atol=1e-6, rtol=1e-4, msg=n)


def test_switches_from_environment():
    """OMNIRECON_FAST sets switches for any command: the reference twins, or name=value pairs."""
    assert fast.from_env(None) == fast.FastPaths()
    ref = fast.from_env("reference")
    assert all(getattr(ref, k) == v for k, v in fast.REFERENCE.items())
    fp = fast.from_env("compile=1, render_batch=64")
    assert fp.compile is True and fp.render_batch == 64 and fp.inference_mode is True
    with pytest.raises(ValueError, match="OMNIRECON_FAST"):
        fast.from_env("warp_speed=9")
    with pytest.raises(ValueError, match="not a switch"):
        fast.from_env("fine_pass=0")


def test_reference_twins_share_signatures():
    """Every reference twin has a fast namesake with the same signature (gsplat's pattern)."""
    import inspect

    from omnirecon.models import reference

    twins = [n for n, f in vars(reference).items() if inspect.isfunction(f) and f.__module__ == reference.__name__]
    assert len(twins) >= 6
    for n in twins:
        assert inspect.signature(getattr(fast, n)) == inspect.signature(getattr(reference, n)), n


@pytest.mark.parametrize("views", [1, 2, 5])
def test_concat_linear_equals_reference(views):
    """The split first layer: forward to 1e-6 of one Linear on the concatenation, whichever part is the
    larger (a per-sample part ``[R, S, 1, A]`` beside per-view parts, and a one-channel part)."""
    from omnirecon.models import reference

    torch.manual_seed(0)
    layer = torch.nn.Linear(6 + 4 + 1, 7)
    parts = [torch.randn(3, 4, 1, 6), torch.randn(3, 4, views, 4), torch.randn(3, 4, views, 1)]
    ref = reference.concat_linear(layer, parts)
    with fast.switches(split_linear=True):
        out = fast.concat_linear(layer, parts)
    assert out.shape == ref.shape == (3, 4, views, 7)
    torch.testing.assert_close(out, ref, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("native", [False, True])
def test_a_models_bf16_preference_applies_only_where_bf16_is_native(monkeypatch, native):
    """A model's own bf16 choice (gpnr-tiny's ``render_bf16``) autocasts only on a CPU that computes bf16 natively
    (emulated bf16 on an AVX2 CPU ran gpnr-tiny's transformers 7x slower than fp32); ``bf16_render=True`` forces it
    and ``False`` forbids it anywhere."""
    monkeypatch.setattr(fast, "_cpu_bf16", lambda: native)
    assert fast.native_bf16("cpu") is native
    with fast.rendering(), fast.net_autocast("cpu", prefer=True):
        assert torch.is_autocast_enabled("cpu") is native
    with fast.rendering(), fast.net_autocast("cpu", prefer=False):
        assert not torch.is_autocast_enabled("cpu")
    with fast.switches(bf16_render=True), fast.rendering(), fast.net_autocast("cpu"):
        assert torch.is_autocast_enabled("cpu")
    with fast.switches(bf16_render=False), fast.rendering(), fast.net_autocast("cpu", prefer=True):
        assert not torch.is_autocast_enabled("cpu")
