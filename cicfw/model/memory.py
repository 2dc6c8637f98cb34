"""``speed.keep_memory``: let glibc's malloc keep freed memory in the process instead of returning it.

A training step allocates and frees activations of tens of MB. By default glibc serves every block
above its mmap threshold with fresh pages from the kernel and hands them back when freed, so each step
page-faults the same memory in again (tens of thousands of faults a step, a tenth of the CPU time in
the kernel). Raising the mmap and trim thresholds keeps freed blocks in the heap for the next step:
the same arithmetic on the same values, without the faults (tests/test_keep_memory.py checks both).
The process holds its peak memory from then on. Process-wide and not undone; glibc only (elsewhere a
no-op with the reason logged).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import platform

# glibc's mallopt parameters (malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
#: blocks up to 1 GB come from the heap, not from mmap (a batch of 120 needs blocks of up to ~50 MB)
MMAP_THRESHOLD = 1 << 30
#: free memory at the heap's top is returned to the kernel only above 2 GB
TRIM_THRESHOLD = (1 << 31) - 1


def keep_freed_memory() -> str | None:
    """Set the thresholds; None when they are set, else the reason they could not be (one line)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return f"not glibc ({platform.system()} {'/'.join(platform.libc_ver()) or 'unknown libc'})"
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        ok = libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1 and libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
    except (OSError, AttributeError) as err:
        return f"mallopt unavailable ({err})"
    return None if ok else "mallopt refused the thresholds"
