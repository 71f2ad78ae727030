"""Keep freed memory in the process for the image-level twin (glibc only).

Rendering a frame allocates and frees a few hundred MB of temporary arrays (supersampled images, depth buffers). With
glibc's defaults, blocks of that size are mapped and unmapped on every frame, or trimmed back to the system when
freed, so every frame page-faults all of it in again: measured 98,600 minor page faults and about as much system
CPU time as user time per frame. Raising the mmap and trim thresholds keeps the freed blocks for the next frame
(0 faults, system time ~0; the process keeps its peak size). Applied once, by the processes that import the renderer
(tests, the demo, the simulated bench, the accuracy benchmark), never by the service or the drivers.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
#: glibc's largest accepted mmap threshold on 64-bit (HEAP_MAX_SIZE / 2)
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
TRIM_THRESHOLD_BYTES = 1024 * 1024 * 1024

_done = False


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds (idempotent); False where there is no glibc ``mallopt``."""
    global _done
    if _done:
        return True
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _done = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
    return _done
