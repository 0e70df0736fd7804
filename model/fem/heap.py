"""glibc's heap held through a solve and given back after it: no page faults for the arrays a Newton iteration frees and
allocates again.

A 10-node solve frees and allocates the same large arrays every iteration (the tangent's CSR data, 15 MB on the
7 mm prostate; CHOLMOD's factor, 65 MB, and its workspace). glibc serves a block over its mmap threshold (32 MB at
most, adjusted at run time) by mmap and unmaps it on free, and trims the heap's top past 128 kB: each iteration then
faults its pages in again, zeroed by the kernel, some 20 000 faults a factorisation. On the two-core machine that was
3 s of system time in a 14 s solve of ``builtin:converged`` at (3,1,2) kPa (bench/README.md, "The 10-node solve's
speed"). :func:`solving` keeps freed memory in the heap for the solve's duration and gives it back (``malloc_trim``)
when the solve ends, so a long-running process (the daemon, a Dask worker) holds between solves only what it uses.
Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

# mallopt's parameters (malloc.h)
M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3
#: The settings a solve runs with: nothing mmapped up to 1 GiB (past the largest factor of a model this machine
#: solves), the heap grown 256 MiB at a time and never trimmed by free (mallopt's values are C ints).
SOLVING_SETTINGS = ((M_MMAP_THRESHOLD, 1 << 30), (M_TOP_PAD, 256 << 20), (M_TRIM_THRESHOLD, 2**31 - 1))

_libc: Any = None
_depth = 0


def _glibc() -> Any:
    """The C library when it is glibc (mallopt and malloc_trim), else None."""
    global _libc
    if _libc is None:
        _libc = False
        if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
            library = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            library.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
            library.malloc_trim.argtypes = [ctypes.c_size_t]
            _libc = library
    return _libc or None


@contextmanager
def solving() -> Iterator[None]:
    """Within: freed memory stays in the process's heap (no unmapping, no trimming). After the outermost: the heap's
    free pages go back to the system (``malloc_trim(0)``), and freed blocks are trimmed or unmapped as glibc's own
    thresholds would (the trim threshold back at its default 128 kB; the mmap threshold stays fixed at 32 MB, the
    dynamic one's ceiling)."""
    global _depth
    libc = _glibc()
    if libc is not None and _depth == 0:
        for parameter, value in SOLVING_SETTINGS:
            libc.mallopt(parameter, value)
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if libc is not None and _depth == 0:
            libc.mallopt(M_MMAP_THRESHOLD, 32 << 20)
            libc.mallopt(M_TOP_PAD, 0)
            libc.mallopt(M_TRIM_THRESHOLD, 128 << 10)
            libc.malloc_trim(0)


def give_back() -> None:
    """The heap's free pages back to the system now (``malloc_trim(0)``), unless a solve is keeping them
    (:func:`solving`); nothing where the C library is not glibc. For a process that freed much at once (the
    daemon's API after closing many clients that each held a long partial line: 107 MB kept, 12 MB after)."""
    libc = _glibc()
    if libc is not None and _depth == 0:
        libc.malloc_trim(0)
