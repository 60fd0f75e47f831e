"""Freed memory kept for reuse by the C library's allocator (glibc), set once per process.

A forward pass allocates and frees tensors of a few MB in every block. By default glibc hands
such blocks back to the system (blocks over its mmap threshold, and the heap's free top), so
the next block's tensors are new pages, each paying its first touch again: at ViT-S size on
CPU that was about 10 % of an extraction's time (30,000 page faults per batch of four images,
DINOv3 S/16). PyTorch's CPU performance guide recommends an allocator that reuses memory
(jemalloc, tcmalloc); glibc does with two settings. Elsewhere (macOS, Windows, musl) nothing
changes.
"""
from __future__ import annotations

import ctypes
import functools
import sys

#: glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: blocks up to this size come from the heap and are reused (glibc's largest allowed value on 64-bit)
MMAP_THRESHOLD = 32 * 2**20
#: free memory at the heap's top is kept, not given back, up to this much
TRIM_THRESHOLD = 256 * 2**20


@functools.cache
def keep_freed_memory() -> bool:
    """Tell glibc to keep freed blocks for reuse (once per process); True when it took both settings."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # glibc, not musl
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) & bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
