"""Freed memory kept for the next step, not returned to the kernel between steps.

A served step allocates a few arrays of about a megabyte (a face card's 300 x 300 system,
its S S^T, LAPACK's work) and frees them. glibc's malloc maps allocations that large
(above its threshold, 128 KiB to start) fresh from the kernel and unmaps them on free, so
every step touches them page by page anew: on two AVX2 cores the page faults cost about
1.5 ms of a large step's 9.5 ms route (`deepcontact bench face-solve`). Raising the mapping
threshold and the trim threshold keeps those pages in the heap, where the next step finds
them warm. A server's memory then stays near its peak step's, a few tens of MiB.
"""

from __future__ import annotations

import ctypes
import ctypes.util

#: glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: Allocations up to this many bytes come from the heap (glibc's largest setting is 32 MiB on
#: 64-bit hosts: HEAP_MAX / 2).
MMAP_THRESHOLD = 32 << 20
#: Free memory at the heap's top kept up to this many bytes before it is returned.
TRIM_THRESHOLD = 256 << 20


def keep_freed_memory() -> bool:
    """Set glibc's malloc to keep freed memory for reuse (the module says why). True where it
    took; False on a C library without mallopt (musl, macOS), where nothing changes."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
