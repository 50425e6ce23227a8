"""Switches of the lean hot path, and the fast functions they choose. Every switch is a speed twin: its
"off" value runs the plain fp32 eager reference twin, a function of the same name and signature in
:mod:`omnirecon.models.reference` (gsplat's pattern), and the fast path agrees with it to the
tolerance ``tests/models/test_fast_paths.py`` states. ``with reference():`` (or
``OMNIRECON_FAST=reference``) turns every switch to its reference twin; ``with switches(name=value):``
sets some of them. Options that change what a model renders are not switches: they are keyword
arguments of ``render_rays`` / ``render_view`` (``fine_pass``, ``surface_samples``: see
:class:`omnirecon.models.base.Capabilities`).

Defaults are on only where the fast path was faster *and* agreed with the reference within the
tolerance its test states (numbers: ``bench/results/fast_paths.json``, ``bench/fast_paths.py``).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache
from weakref import WeakKeyDictionary

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omnirecon.models import reference as _ref
from omnirecon.rays import Rays


@dataclass
class FastPaths:
    """Which fast paths are on. The reference twin of each is its "off" value."""

    inference_mode: bool = True
    """``render_view`` runs under ``torch.inference_mode`` (reference: ``torch.no_grad``)."""
    render_batch: int = 256
    """``render_view`` calls ``render_rays`` on at most this many rays at a time, whatever the memory
    ``chunk``: per-sample tensors of a few MB stay in cache and in the allocator's free lists instead
    of being mapped and page-faulted afresh for every op (0, the reference: ``chunk`` rays per call).
    Small batches render faster than 4096 rays per call (BENCHMARKS "Each fast-path switch against its reference
    twin")."""
    train_batch: int = 128
    """Training forwards (``render_rays_batched``, used by the training loss) render the ray batch in
    sub-batches of at most this many rays, one graph (0, the reference: the whole batch in one call). Faster for
    ibrnet-tiny, about even for gpnr-tiny and omnirecon-tiny (``bench/throughput.py``; BENCHMARKS "Throughput")."""
    preallocate: bool = True
    """``render_view`` writes each batch into preallocated full-image outputs (reference: a list of
    chunks concatenated at the end)."""
    render_workers: int = 0
    """With ``preallocate``, ``render_view`` on the CPU renders its batches on this many threads at once, torch's
    intra-op threads at 1 inside them (the ops release the GIL; each batch is written into its own rows of the
    outputs, so the image is the serial one's bit for bit). 0: ``torch.get_num_threads()`` workers (the
    command's ``--threads``); 1 (the reference): one batch at a time, each op on torch's threads. Small batches
    parallelise poorly inside each op: on 2 cores intra-op threads gave about 1.4x one thread's wall time, and
    batches side by side come closer to 2x (BENCHMARKS "Surface-guided volumetric rendering", 2-thread rows).
    Serial on other devices and with ``compile`` (compiled graphs are not called from several threads)."""
    split_linear: bool = True
    """Per-sample MLPs whose first layer reads a concatenation ``[per-sample stats, per-view features]``
    (IBRNet's base and colour MLPs) apply the layer's column blocks to the parts apart: the per-sample
    part once per sample instead of once per view, and no concatenated tensor (reference: concat, one
    Linear). Forward and gradients agree to float rounding."""
    compile: bool = False
    """Inside ``render_view``, the per-sample networks run through ``torch.compile`` (one graph per
    network and batch shape; ``render_view`` pads its last batch to the full size so that no shape is
    new), its kernels cached on disk across processes (:func:`compile_cache_dir`). Off: the first compile takes
    minutes on a shared 2-core CPU (much less from inductor's warm disk cache), more than most renders take, for a
    faster tiny aggregator and none for ibrnet-paper's (BENCHMARKS "torch.compile with a persistent cache").
    ``OMNIRECON_FAST=compile=1`` for long jobs."""
    sdpa_attention: bool = True
    """IBRNet's ray transformer calls ``scaled_dot_product_attention`` on its own projections with the
    boolean key mask (reference: ``nn.MultiheadAttention``, which merges the mask into a float one first).
    Same weights and arithmetic; bit-identical on the tests, 2.3x on the attention of ibrnet-paper
    (256 rays x 128 samples, 4 heads of 4 channels, one thread)."""
    inplace_elu: bool = True
    """IBRNet's aggregator applies its ELUs in place on the Linear outputs they follow (reference: a new
    tensor each). Same values; out-of-place ELU on 256 rays x 128 samples x 3 views x 64 channels took
    2x the in-place one (one thread), ~1.16x on the whole aggregator."""
    bf16_render: bool | None = None
    """The per-sample networks (IBRNet's aggregator, GPNR's transformers, Omni-Recon's geometry and
    appearance branches) run under bf16 autocast inside ``render_view``; their outputs are cast back
    and everything geometric stays fp32 (reference, False: fp32 throughout). None: each model's own choice
    (GPNR's ``render_bf16``, on in the shipped gpnr-tiny; the others fp32): GPNR gains most, IBRNet and
    Omni-Recon little; the render stays close to the fp32 one (``tests/models/test_fast_paths.py`` holds the
    tolerance; speed: BENCHMARKS "Each fast-path switch against its reference twin")."""


def from_env(text: str | None) -> FastPaths:
    """Switches from ``OMNIRECON_FAST``: ``reference`` (every reference twin) and/or comma-separated
    ``name=value`` pairs, e.g. ``compile=1,render_batch=512`` (any command, no code change)."""
    fp = FastPaths()
    for item in filter(None, (t.strip() for t in (text or "").split(","))):
        if item == "reference":
            fp = dataclasses.replace(fp, **REFERENCE)
            continue
        name, _, value = item.partition("=")
        if name in ("fine_pass", "surface_samples"):
            raise ValueError(f"OMNIRECON_FAST: {name} changes the output, so it is not a switch; it is an argument "
                             "of render_view / render_rays (mesh: --depth-pass coarse)")
        kind = {f.name: f.type for f in dataclasses.fields(FastPaths)}.get(name)
        if kind is None or not value:
            raise ValueError(f"OMNIRECON_FAST: bad item {item!r}; use reference or name=value with a name of "
                             f"{', '.join(f.name for f in dataclasses.fields(FastPaths))}")
        setattr(fp, name, int(value) if kind in (int, "int") else value.lower() in ("1", "true", "yes", "on"))
    return fp


REFERENCE = {"inference_mode": False, "render_batch": 0, "train_batch": 0, "preallocate": False, "render_workers": 1,
             "split_linear": False,
             "compile": False, "bf16_render": False,
             "sdpa_attention": False, "inplace_elu": False}
"""Every switch at its reference-twin value."""

FAST = from_env(os.environ.get("OMNIRECON_FAST"))
"""The process-wide switches read by the models (defaults, or ``OMNIRECON_FAST``)."""


_RENDERING = [0]
"""Depth of nested ``render_view`` calls (bf16 autocast and compiled networks apply only inside one)."""


@contextmanager
def rendering():
    """Marks the block as rendering (``render_view``): ``net_autocast`` and ``compiled`` may act inside it."""
    _RENDERING[0] += 1
    try:
        yield
    finally:
        _RENDERING[0] -= 1


# ---------------------------------------------------------------------- fast functions (twins: reference.py)
def grad_mode():
    """``torch.inference_mode()`` when ``FAST.inference_mode``; else the reference's ``torch.no_grad()``."""
    return torch.inference_mode() if FAST.inference_mode else _ref.grad_mode()


def is_rendering() -> bool:
    """Inside ``render_view`` (render options of a model's config apply there only, never in training)."""
    return _RENDERING[0] > 0


def net_autocast(device: torch.device | str, prefer: bool = False):
    """bf16 autocast for a model's per-sample networks when rendering and ``FAST.bf16_render`` is True, or is
    None and the model ``prefer``s it (its config); else the reference (none). Geometry (projection, sample
    positions, compositing) stays in the sources' dtype: callers cast the networks' outputs back."""
    on = (prefer and native_bf16(device)) if FAST.bf16_render is None else FAST.bf16_render
    if not (on and _RENDERING[0]):
        return _ref.net_autocast(device)
    return torch.autocast(device_type=torch.device(device).type, dtype=torch.bfloat16)


@lru_cache(maxsize=None)
def _cpu_bf16() -> bool:
    probe = getattr(torch.cpu, "_is_avx512_bf16_supported", None), getattr(torch.cpu, "_is_amx_tile_supported", None)
    return any(f is not None and f() for f in probe)


def native_bf16(device: torch.device | str) -> bool:
    """Whether bf16 arithmetic is native on ``device``: a CUDA device that supports it, or a CPU with AVX512-BF16 or
    AMX. Elsewhere (AVX2 x86, most ARM builds) it is emulated: gpnr-tiny's transformers under bf16 autocast took
    several times their fp32 time on an AVX2 EPYC, so a model's own
    preference for bf16 (``prefer``) applies only where this is True; ``FastPaths.bf16_render`` and ``render
    --precision bf16`` still force it."""
    kind = torch.device(device).type
    return _cpu_bf16() if kind == "cpu" else kind == "cuda" and torch.cuda.is_bf16_supported()


_COMPILED: WeakKeyDictionary = WeakKeyDictionary()


def compiled(module: nn.Module):
    """(``FAST.compile`` inside ``render_view``) the ``torch.compile``d twin of ``module``, made once; else
    the reference: ``module`` itself."""
    if not (FAST.compile and _RENDERING[0]):
        return _ref.compiled(module)
    fn = _COMPILED.get(module)
    if fn is None:
        os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(compile_cache_dir()))
        fn = _COMPILED[module] = torch.compile(module, dynamic=False)
    return fn


def compile_cache_dir() -> str:
    """Where ``FAST.compile`` keeps inductor's compiled kernels across processes and reboots (unless
    ``TORCHINDUCTOR_CACHE_DIR`` is set): ``$XDG_CACHE_HOME/omnirecon/inductor`` (``~/.cache/...``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "omnirecon", "inductor")


def concat_linear(layer: nn.Linear, parts: list[Tensor]) -> Tensor:
    """``layer`` on the concatenation of ``parts`` (broadcast along the leading axes), as
    :func:`omnirecon.models.reference.concat_linear`. With ``FAST.split_linear`` the layer's column
    blocks apply to the parts apart, and the sum is broadcast: a per-sample part ``# [R, S, 1, A]``
    costs once per sample instead of once per view, and no concatenated tensor is made. The bias goes
    with the part of the most rows (the first of them: a per-view part), which is computed first; the
    others are added in order (float rounding apart, the same sum). ``# [..., out]``"""
    if not FAST.split_linear:
        return _ref.concat_linear(layer, parts)
    cols, start = [], 0
    for p in parts:
        cols.append(layer.weight[:, start:start + p.shape[-1]])
        start += p.shape[-1]
    first, rows = 0, parts[0].shape[:-1].numel()  # a loop, not max(key=...): no graph break under torch.compile
    for i in range(1, len(parts)):
        if parts[i].shape[:-1].numel() > rows:
            first, rows = i, parts[i].shape[:-1].numel()
    out = F.linear(parts[first], cols[first], layer.bias)
    for i, (p, w) in enumerate(zip(parts, cols)):
        if i != first:
            out = out + (p * w[:, 0] if p.shape[-1] == 1 else F.linear(p, w))
    return out


def render_batches(render: Callable[[Rays, int], dict[str, Tensor]], rays: Rays, batch: int, height: int, width: int
                   ) -> dict[str, Tensor]:
    """``render(part, start)`` on consecutive batches ``part`` of at most ``batch`` of ``rays`` (``start``: the index
    of its first ray), per-ray outputs reshaped to ``[height, width, ...]`` (as
    :func:`omnirecon.models.reference.render_batches`). With ``FAST.preallocate`` each batch is written into
    full-image buffers made once (floating outputs in the rays' dtype), with ``FAST.compile`` the last batch is
    padded to the full size (compiled graphs keep one shape), and on the CPU the batches after the first run on
    :func:`render_workers` threads. Called under the caller's grad mode, which each worker enters too."""
    if not FAST.preallocate:
        return _ref.render_batches(render, rays, batch, height, width)
    n, bufs = len(rays), {}
    float_dtype = rays.origins.dtype

    def one(start: int) -> None:
        m = min(batch, n - start)
        if FAST.compile and m < batch < n:  # pad the last batch: compiled graphs keep one shape
            part = rays[torch.arange(start, start + batch, device=rays.origins.device).clamp_max(n - 1)]
        else:
            part = rays[start:start + m]
        out = {k: v[:m] if v.dim() >= 1 and v.shape[0] == len(part) else v for k, v in render(part, start).items()}
        if not bufs:  # one buffer per per-ray output (the first batch, before any worker starts), filled in place
            bufs.update({k: torch.empty((n, *v.shape[1:]), device=v.device,
                                        dtype=float_dtype if v.is_floating_point() else v.dtype)
                         for k, v in out.items() if v.dim() >= 1 and v.shape[0] == m})
        for k, buf in bufs.items():
            buf[start:start + m] = out[k]

    starts = list(range(0, n, batch))
    workers = render_workers(rays.origins.device)
    if len(starts) - 1 < PARALLEL_BATCHES * workers:  # a small image: the pool costs more than it saves
        workers = 1
    if starts:
        one(starts[0])
    if workers > 1:
        _parallel(one, starts[1:], workers)
    else:
        for start in starts[1:]:
            one(start)
    return {k: v.reshape(height, width, *v.shape[1:]) for k, v in bufs.items()}


PARALLEL_BATCHES = 4
""":func:`render_batches` renders side by side only with at least this many batches per worker after the first
(fewer: serially): on a 20x24 view of two batches the pool and the thread-count switches cost more than they save."""


def render_workers(device: torch.device) -> int:
    """Threads :func:`render_batches` renders batches on (``FastPaths.render_workers``; 1 off the CPU and with
    ``compile``)."""
    if torch.device(device).type != "cpu" or FAST.compile or not FAST.preallocate:
        return 1
    return FAST.render_workers if FAST.render_workers > 0 else torch.get_num_threads()


def _parallel(fn: Callable[[int], None], starts: list[int], workers: int) -> None:
    """``fn(start)`` for every start on ``workers`` threads, each under the caller's grad mode with one intra-op
    torch thread (restored after); the first error is raised here."""
    from concurrent.futures import ThreadPoolExecutor

    inference, grad = torch.is_inference_mode_enabled(), torch.is_grad_enabled()
    threads = torch.get_num_threads()

    def run(start: int) -> None:
        torch.set_num_threads(1)
        mode = torch.inference_mode() if inference else torch.set_grad_enabled(grad)
        with mode:
            fn(start)

    torch.set_num_threads(1)
    try:
        with ThreadPoolExecutor(workers, thread_name_prefix="render") as pool:
            for f in [pool.submit(run, s) for s in starts]:
                f.result()
    finally:
        torch.set_num_threads(threads)


def render_sub_batches(render: Callable[[Rays], dict[str, Tensor]], rays: Rays, batch: int) -> dict[str, Tensor]:
    """A training forward of ``rays`` (graph kept). With ``FAST.train_batch`` > 0 (``batch``) ``render``
    runs on sub-batches of at most ``batch`` rays and the per-ray outputs are concatenated: every model
    renders each ray independently, so outputs and gradients are those of one call up to float rounding
    (the reference: one call)."""
    n = len(rays)
    if batch <= 0 or n <= batch:
        return _ref.render_sub_batches(render, rays, batch)
    parts = [render(rays[s:s + batch]) for s in range(0, n, batch)]
    sizes = [min(batch, n - s) for s in range(0, n, batch)]
    return {k: torch.cat([p[k] for p in parts]) if all(p[k].dim() >= 1 and p[k].shape[0] == m
                                                      for p, m in zip(parts, sizes)) else v
            for k, v in parts[0].items()}


# ---------------------------------------------------------------------- switching
@contextmanager
def reference():
    """Every switch at its reference twin (plain fp32 eager) inside the block."""
    with switches(**REFERENCE):
        yield FAST


@contextmanager
def switches(**values):
    """Set some switches inside the block, e.g. ``switches(bf16_render=True)``."""
    names = {f.name for f in dataclasses.fields(FastPaths)}
    unknown = set(values) - names
    if unknown:
        raise AttributeError(f"no fast path {', '.join(sorted(unknown))}; known: {', '.join(sorted(names))}")
    old = {k: getattr(FAST, k) for k in values}
    for k, v in values.items():
        setattr(FAST, k, v)
    try:
        yield FAST
    finally:
        for k, v in old.items():
            setattr(FAST, k, v)
