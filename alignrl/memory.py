"""Memory a process frees stays in it for the next array (glibc's allocator, tuned once).

The focus posterior (alignrl/posterior/inference.py) makes and drops arrays of 15 MB at
every reading (1,024 columns x 1,836 optimum grid points; a calibration's search, 256 columns
x 3 specimen points x up to 4,000, 20-25 MB), several temporaries per line. glibc serves a
block above its mmap threshold with fresh pages from the kernel and hands them back when it
is freed, and hands back the heap's free top above its trim threshold; it raises both by
itself only as far as 32 MiB (twice that for the trim) and after the fact, so such arrays
keep being faulted in page by page. Where page faults are dear that is time the numbers
never needed: on this project's 2-core machine `alignrl evaluate --policy posterior-robust
--apparatus instrument:val-mid --scenarios 2` took 26.0 s with glibc's defaults and 22.4 s
tuned, its system time 4.8 s against 2.2 s (`python -m benchmarks.allocator`,
docs/benchmarks.md).

`keep_freed_memory` raises both thresholds to `KEPT_BYTES`: blocks up to 1 GiB come from the
heap, and freed memory is reused rather than returned until over 1 GiB of it lies free at
the top. The numbers computed are the same bit for bit; the process's resident size stays
near its peak instead of falling back after each step. `alignrl` (every verb), the
benchmarks, the recorder's worker processes and the Ray workers call it at start; a library
user may call it too.

It is left alone where glibc is not the C library (macOS, musl: nothing to tune there), where
the environment already sets glibc's malloc options (MALLOC_MMAP_THRESHOLD_,
MALLOC_TRIM_THRESHOLD_, MALLOC_TOP_PAD_, GLIBC_TUNABLES: the user's choice stands), and where
ALIGNRL_MALLOC=system asks for glibc's defaults. ALIGNRL_MALLOC=tuned (or unset, or empty) is
the tuning; any other value is a ValueError naming the variable and the values it takes
(`check_malloc_choice`), never a typo silently read as the tuning.
"""

from __future__ import annotations

import ctypes
import os
from collections.abc import Mapping

__all__ = [
    "KEPT_BYTES",
    "MALLOC_CHOICES",
    "check_malloc_choice",
    "keep_freed_memory",
    "without_malloc_choices",
]

KEPT_BYTES = 1 << 30  # blocks up to this come from the heap; this much free is kept
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
_USER_OPTIONS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_",
                 "GLIBC_TUNABLES")  # fmt: skip
_applied: bool | None = None  # what the first call did (a process tunes once)
MALLOC_VARIABLE = "ALIGNRL_MALLOC"
# Its values (any case, spaces around ignored): the tuning, or glibc's defaults; unset or
# empty is the tuning.
MALLOC_CHOICES = {"tuned": "freed memory kept for reuse, the default", "system": "glibc's defaults"}
SHOWN_VALUE = 40  # characters of an unknown value echoed in the message


def check_malloc_choice() -> str:
    """ALIGNRL_MALLOC's choice, "tuned" or "system" (unset or empty: "tuned"); ValueError
    naming the variable, its value and the values it takes for any other value. Cheap: a
    command may call it where its errors are reported, before `keep_freed_memory`."""
    value = os.environ.get(MALLOC_VARIABLE, "")
    choice = value.strip().lower() or "tuned"
    if choice not in MALLOC_CHOICES:
        shown = value if len(value) <= SHOWN_VALUE else f"{value[:SHOWN_VALUE]}..."
        accepted = ", ".join(f"{name} ({meaning})" for name, meaning in MALLOC_CHOICES.items())
        raise ValueError(
            f"environment variable {MALLOC_VARIABLE}={shown!r} is not one of its values: "
            f"{accepted}; or leave it unset"
        )
    return choice


def keep_freed_memory() -> bool:
    """Tune glibc to keep freed memory for reuse (module docstring), once per process.
    Returns whether the thresholds are now raised: False where the C library is not glibc,
    the environment sets malloc options already, or ALIGNRL_MALLOC=system. ValueError for
    any other ALIGNRL_MALLOC than tuned or system (`check_malloc_choice`), nothing tuned."""
    global _applied
    if _applied is None:
        _applied = check_malloc_choice() == "tuned" and _tune()
    return _applied


def without_malloc_choices(environment: Mapping[str, str]) -> dict[str, str]:
    """`environment` less every variable that decides whether alignrl tunes glibc
    (ALIGNRL_MALLOC and the user's malloc options): a process started with it tunes."""
    return {
        name: value
        for name, value in environment.items()
        if name != MALLOC_VARIABLE and name not in _USER_OPTIONS
    }


def _tune() -> bool:
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
