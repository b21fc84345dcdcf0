"""Keep freed memory in the process instead of handing it back to the OS after every CQL step: with glibc's defaults
its 11 MB activations are fresh ``mmap`` pages each step, ~20% of the step (``benchmarks/cql_speed.py``). As
``MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=268435456``.
"""

from __future__ import annotations

import ctypes
import sys

#: glibc's ``mallopt`` parameters (malloc.h) and the values set: blocks up to 32 MiB come from the heap, and the heap
#: keeps up to 256 MiB of free memory at its top.
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD, TRIM_THRESHOLD = 32 * 2**20, 256 * 2**20


def retain_freed_memory() -> bool:
    """Set glibc's mmap and trim thresholds for this process; ``False`` where the C library is not glibc."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and other C libraries
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
