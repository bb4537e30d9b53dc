"""Memory a process frees stays in it for the next array (glibc's allocator, tuned once).

The focus posterior (alignrl/apparatus/family_posterior.py) makes and drops arrays of up to
45 MB at every reading: columns by specimen points by optimum grid, several temporaries per
line. By default glibc serves every block above its mmap threshold (128 KiB, raised by itself
up to 32 MiB) with fresh pages from the kernel and hands them back when freed, and trims the
heap's top once 128 KiB lie free there: such an array is faulted in page by page again at
every step. Where page faults are dear (containers and sandboxes) that is time the numbers
never needed: `alignrl evaluate --policy posterior-robust --apparatus instrument:val-mid
--scenarios 2` took 26.0 s with glibc's defaults and 22.4 s tuned, its system time 4.8 s
against 2.2 s (`python -m benchmarks.allocator`, docs/benchmarks.md).

`keep_freed_memory` raises both thresholds to `KEPT_BYTES`: blocks up to 1 GiB come from the
heap, and freed memory is reused rather than returned until over 1 GiB of it lies free at
the top. The numbers computed are the same bit for bit; the process's resident size stays
near its peak instead of falling back after each step. `alignrl` (every verb), the
benchmarks, the recorder's worker processes and the Ray workers call it at start; a library
user may call it too.

It is left alone where glibc is not the C library (macOS, musl: nothing to tune there), where
the environment already sets glibc's malloc options (MALLOC_MMAP_THRESHOLD_,
MALLOC_TRIM_THRESHOLD_, MALLOC_TOP_PAD_, GLIBC_TUNABLES: the user's choice stands), and where
ALIGNRL_MALLOC=system asks for glibc's defaults.
"""

from __future__ import annotations

import ctypes
import os

__all__ = ["KEPT_BYTES", "keep_freed_memory"]

KEPT_BYTES = 1 << 30  # blocks up to this come from the heap; this much free is kept
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
_USER_OPTIONS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_",
                 "GLIBC_TUNABLES")  # fmt: skip
_applied: bool | None = None  # what the first call did (a process tunes once)


def keep_freed_memory() -> bool:
    """Tune glibc to keep freed memory for reuse (module docstring), once per process.
    Returns whether the thresholds are now raised: False where the C library is not glibc,
    the environment sets malloc options already, or ALIGNRL_MALLOC=system."""
    global _applied
    if _applied is None:
        _applied = _tune()
    return _applied


def _tune() -> bool:
    if os.environ.get("ALIGNRL_MALLOC", "").strip().lower() == "system":
        return False
    if any(name in os.environ for name in _USER_OPTIONS):
        return False
    try:
        libc = ctypes.CDLL(None)  # the process's own symbols: its C library's among them
    except OSError:
        return False
    if not (hasattr(libc, "gnu_get_libc_version") and hasattr(libc, "mallopt")):
        return False  # not glibc: no mallopt, or one of another meaning
    mallopt = libc.mallopt
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # mmap first: a trim threshold set alone would leave blocks over 32 MiB to mmap
    return bool(mallopt(_M_MMAP_THRESHOLD, KEPT_BYTES) and mallopt(_M_TRIM_THRESHOLD, KEPT_BYTES))
