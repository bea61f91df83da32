"""Keep freed memory in the process so that the filter's per-step tensors do not page-fault.

A filter step allocates and frees tensors of a few MB (C = 100 points x 4098 observation
entries in float64 is 3.3 MB). glibc's malloc serves blocks that large with fresh ``mmap`` pages
or trims them off the heap when they are freed, so the next step touches new pages: about 1,600
minor page faults a step, a quarter of its time. Raising the mmap and trim thresholds keeps
those blocks on the heap for reuse. The cost is that the process holds on to up to
``TRIM_THRESHOLD_BYTES`` of freed memory.

The ``vistac`` command calls ``keep_freed_memory`` at start; Python users running a skill in a
time-critical loop can call it themselves. Setting either ``MALLOC_MMAP_THRESHOLD_`` or
``MALLOC_TRIM_THRESHOLD_`` in the environment leaves the allocator as the user set it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
"""glibc's upper limit for the mmap threshold on 64-bit systems."""
TRIM_THRESHOLD_BYTES = 256 * 1024 * 1024
USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")


def keep_freed_memory() -> bool:
    """Set glibc's mmap threshold to 32 MB and its trim threshold to 256 MB (both settings are
    needed: either alone turns off glibc's own adaptive threshold and makes it worse).
    Returns whether the allocator was changed: False without glibc's ``mallopt`` or when the
    user set the thresholds in the environment."""
    if any(name in os.environ for name in USER_SETTINGS):
        log.debug("malloc thresholds left as the environment sets them")
        return False
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError, TypeError):
        log.debug("no mallopt in the C library %s; allocator unchanged", name)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    changed = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
    log.debug("malloc mmap/trim thresholds raised: %s", changed)
    return changed
