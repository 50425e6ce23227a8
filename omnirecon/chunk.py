"""The default ``--chunk`` (rays rendered at once) from the machine's memory, and a note when a chosen one
would exceed the ceiling.

Peak memory grows with the chunk by about :data:`BYTES_PER_RAY` (peak resident memory at a large ``--chunk``
over the chunk, dominated by the per-sample features of the K source views). The
ceiling is :data:`FRACTION` of the RAM; the default is the largest power of two whose estimate fits in
that fraction of the memory available now, at most :data:`DEFAULT_MAX` (what every command used before)
and at least :data:`MIN_CHUNK`.
"""

from __future__ import annotations

import sys

from omnirecon.memory import memory_bytes

BYTES_PER_RAY = 140_000
"""Peak-memory growth per ray of the chunk (bytes), measured."""
FRACTION = 0.25
"""Share of the RAM a chunk may take."""
DEFAULT_MAX = 4096
"""The default never exceeds the former fixed default."""
MIN_CHUNK = 256


def ceiling(total: int | None = None) -> int:
    """The largest chunk whose estimated memory stays within ``FRACTION`` of the RAM."""
    total = memory_bytes()[0] if total is None else total
    return max(MIN_CHUNK, int(FRACTION * total / BYTES_PER_RAY))


def default_chunk(available: int | None = None) -> int:
    """The largest power of two <= ``DEFAULT_MAX`` whose estimate fits in ``FRACTION`` of ``available``."""
    available = memory_bytes()[1] if available is None else available
    fit = int(FRACTION * available / BYTES_PER_RAY)
    chunk = DEFAULT_MAX
    while chunk > MIN_CHUNK and chunk > fit:
        chunk //= 2
    return chunk


def pick_chunk(chunk: int | None, flag: str = "--chunk") -> int:
    """``chunk`` when given (with a one-line note on stderr when it exceeds :func:`ceiling`), else
    :func:`default_chunk`. Values below 1 are returned as they are, for the command's own check."""
    if chunk is None:
        return default_chunk()
    total = memory_bytes()[0]
    if chunk > ceiling(total):
        print(f"omnirecon: note: {flag} {chunk} needs about {chunk * BYTES_PER_RAY / 1e9:.1f} GB "
              f"(~{BYTES_PER_RAY // 1000} kB per ray), above {FRACTION:.0%} of this machine's "
              f"{total / 1e9:.1f} GB of RAM (ceiling {ceiling(total)}); lower it if the run runs out of memory",
              file=sys.stderr)
    return chunk
