"""The reference twins of the fast paths in :mod:`omnirecon.models.fast`: plain fp32 eager PyTorch, the
code each fast path must agree with (gsplat's pattern: the fast function and its pure-torch reference
live apart, with the same signature).

Each function here has a namesake in :mod:`omnirecon.models.fast`, which runs it when its switch is
off (``with reference():`` or ``OMNIRECON_FAST=reference``); ``tests/models/test_fast_paths.py`` holds
each pair to the tolerance it states. Nothing here reads a switch.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import nullcontext

import torch
from torch import Tensor, nn

from omnirecon.rays import Rays


def grad_mode():
    """The autograd mode ``render_view`` renders in: ``torch.no_grad()``."""
    return torch.no_grad()


def net_autocast(device: torch.device | str, prefer: bool = False):
    """The per-sample networks in the sources' dtype: no autocast (whatever the model ``prefer``s)."""
    return nullcontext()


def compiled(module: nn.Module):
    """The per-sample network as it is (eager)."""
    return module


def concat_linear(layer: nn.Linear, parts: list[Tensor]) -> Tensor:
    """``layer`` on the concatenation of ``parts`` along the last axis, each broadcast to the common
    leading shape first (e.g. per-sample stats ``# [R, S, 1, A]`` beside per-view features
    ``# [R, S, V, B]``). ``# [..., out]``"""
    shape = torch.broadcast_shapes(*(p.shape[:-1] for p in parts))
    return layer(torch.cat([p.expand(*shape, -1) for p in parts], -1))


def render_batches(render: Callable[[Rays, int], dict[str, Tensor]], rays: Rays, batch: int, height: int, width: int
                   ) -> dict[str, Tensor]:
    """``render(part, start)`` on consecutive batches ``part`` of at most ``batch`` of ``rays`` (one image's,
    row-major; ``start``: the index of its first ray), one after another, the per-ray outputs gathered in lists,
    concatenated and reshaped to ``[height, width, ...]``; outputs that are not per ray are dropped."""
    parts: dict[str, list[Tensor]] = {}
    for start in range(0, len(rays), batch):
        out = render(rays[start:start + batch], start)
        for k, v in out.items():
            if v.dim() >= 1 and v.shape[0] == min(batch, len(rays) - start):
                parts.setdefault(k, []).append(v)
    return {k: torch.cat(v).reshape(height, width, *v[0].shape[1:]) for k, v in parts.items()}


def render_sub_batches(render: Callable[[Rays], dict[str, Tensor]], rays: Rays, batch: int) -> dict[str, Tensor]:
    """A training forward of ``rays``: one ``render`` call on the whole batch (``batch`` is not used)."""
    return render(rays)
