"""The C allocator's policy for large arrays (glibc on Linux): keep freed memory in the process's heap.

glibc serves every allocation above its mmap threshold (at most 32 MiB) by a fresh ``mmap`` and returns it to the
system on ``free``: each new volume of 256^3 float32 values (64 MiB) is then page-faulted in afresh, and on the
CPU that costs as much as the arithmetic. Measured on the 2-core reference machine, one thread, 256^3: a SIRT
iteration 2.45 s -> 1.33 s, the 61-tilt forward and adjoint 0.92 s -> 0.65 s; 96^3 phantoms 3x (before their
slabs were made small). :func:`use_heap_allocator` turns ``mmap`` off for ``malloc`` (``M_MMAP_MAX = 0``) and
keeps up to 2 GiB of freed memory (``M_TRIM_THRESHOLD``): the peak memory is unchanged, what a run frees is
reused instead of returned. The app (``indreg-register``) calls it at start; a Python user can call it, or export
``GLIBC_TUNABLES=glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=2147483647`` before starting Python.
``INDREG_MALLOC=system`` leaves the allocator as it is. Elsewhere (macOS, Windows, musl) it does nothing.

:func:`system_allocator` puts glibc's default policy back for a while: the app builds its data there (the 3D
phantoms' many float64 temporaries, kept in the heap, fragment it: at 256^3 building the data peaked at 2.44 GiB
with the heap policy, 1.20 GiB without).
"""
from __future__ import annotations

import ctypes
import os
import sys
from contextlib import contextmanager

M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
TRIM_THRESHOLD = 2 ** 31 - 1   # mallopt takes an int
#: glibc's defaults: the most mapped blocks, the trim threshold (bytes).
DEFAULT_MMAP_MAX, DEFAULT_TRIM_THRESHOLD = 65536, 128 * 1024
_heap = False   # use_heap_allocator's settings are in force


def use_heap_allocator() -> bool:
    """Keep large freed blocks in the heap (module docstring). Returns True when glibc accepted both settings."""
    if not sys.platform.startswith("linux") or os.environ.get("INDREG_MALLOC", "").lower() == "system":
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):   # not glibc
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    global _heap
    _heap = mallopt(M_MMAP_MAX, 0) == 1 and mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
    return _heap


@contextmanager
def system_allocator():
    """glibc's default policy inside the block when :func:`use_heap_allocator` set the heap's (then back to it)."""
    if not _heap:
        yield
        return
    mallopt = ctypes.CDLL("libc.so.6").mallopt
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    mallopt(M_MMAP_MAX, DEFAULT_MMAP_MAX)
    mallopt(M_TRIM_THRESHOLD, DEFAULT_TRIM_THRESHOLD)
    try:
        yield
    finally:
        use_heap_allocator()
