"""The machine's memory, read in one place: total RAM, and what a new allocation can get now.

``available`` is ``MemAvailable`` of ``/proc/meminfo`` (``sysconf`` where that is missing) and no more than the
address-space limit (``ulimit -v``) leaves this process, so the chunk default (:mod:`omnirecon.chunk`), the option
checks (:mod:`omnirecon.option_memory`, :func:`omnirecon.preflight.check_memory`) and the photo loader agree.
"""

from __future__ import annotations

import os
import resource


def _meminfo() -> dict[str, int]:
    """``/proc/meminfo`` in bytes (empty where it cannot be read)."""
    info = {}
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                key, _, rest = line.partition(":")
                info[key] = int(rest.split()[0]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return info


def _address_space_left() -> int | None:
    """Bytes the address-space limit (``ulimit -v``) leaves this process, or ``None`` when there is no limit."""
    limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    if limit == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/status") as f:
            used = int(next(ln.split()[1] for ln in f if ln.startswith("VmSize:"))) * 1024
    except (OSError, StopIteration, ValueError):
        used = 0
    return max(0, limit - used)


def memory_bytes() -> tuple[int, int]:
    """``(total, available)`` in bytes: the RAM, and what a new allocation can get now (module docstring)."""
    info = _meminfo()
    total = info.get("MemTotal") or os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    avail = info.get("MemAvailable")
    if avail is None:
        avail = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    left = _address_space_left()
    return total, min(avail, total) if left is None else min(avail, total, left)
