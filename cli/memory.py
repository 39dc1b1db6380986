"""Process-level allocator setting for the ``run`` command (Linux/glibc only).

Each frame allocates and frees the same few megabyte-sized numpy buffers (flow,
masks, score maps). With glibc's default, adaptive mmap threshold they are often
handed back to the kernel and faulted in again on the next frame, which measured
as the masks and re-draw stages taking ~50% longer (benchmarks/HOUSE.md). Fixed
thresholds keep freed buffers in the heap for reuse. The command sets this for
its own process only; the library never touches the allocator.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 * 1024 * 1024  # buffers below this come from the heap (glibc's adaptive maximum)
TRIM_THRESHOLD = 128 * 1024 * 1024  # free heap kept before it is returned to the kernel


def keep_freed_buffers() -> bool:
    """Set fixed glibc malloc thresholds; returns whether they were set (False off glibc)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
