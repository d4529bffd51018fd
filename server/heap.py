"""Freed memory kept for the next step, not returned to the kernel between steps.

A served step allocates a few arrays of about a megabyte (a face card's 300 x 300 system,
its S S^T, LAPACK's work) and frees them. glibc's malloc maps allocations that large
fresh from the kernel, or returns the freed top of its heap, depending on thresholds that
start at 128 KiB and move with what was freed; a step that gets fresh pages touches them
one page fault at a time. Fixing the mapping threshold and the trim threshold high keeps
those pages in the heap, where the next step finds them warm. A server's memory then stays
near its peak step's, a few tens of MiB. What it saves on a face card's route is in
`deepcontact lab face-solve` (its "heap as glibc starts" column, the same route with the
thresholds set back to glibc's starting values, paired step by step).
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
#: Both thresholds' starting values in glibc (M_MMAP_THRESHOLD's DEFAULT_MMAP_THRESHOLD_MIN).
GLIBC_START = 128 << 10


def keep_freed_memory(kept: bool = True) -> bool:
    """Set glibc's malloc to keep freed memory for reuse (the module says why), or with
    kept=False set its thresholds to their starting values (fixed there: a measurement's
    control). True where it took; False on a C library without mallopt (musl, macOS), where
    nothing changes."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    mmap, trim = (MMAP_THRESHOLD, TRIM_THRESHOLD) if kept else (GLIBC_START, GLIBC_START)
    return bool(mallopt(_M_MMAP_THRESHOLD, mmap)) and bool(mallopt(_M_TRIM_THRESHOLD, trim))
