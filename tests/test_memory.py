"""alignrl/memory.py: glibc keeps the memory a process frees for its next large array, the
numbers computed stay the same, and a user's own malloc options (or ALIGNRL_MALLOC=system)
are left alone. Each case runs in a process of its own: glibc is tuned once per process."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from alignrl.memory import check_malloc_choice, without_malloc_choices

GLIBC = platform.libc_ver()[0] == "glibc"  # mallinfo2: glibc 2.33 and later

# glibc's own account (mallinfo2) of a 40 MB array: the bytes it took from mmap for it, and
# the free bytes its heap holds once it is freed.
REUSED = """
import ctypes, numpy as np
from alignrl.memory import keep_freed_memory
class Info(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks",
                "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]
mallinfo2 = ctypes.CDLL(None).mallinfo2
mallinfo2.restype = Info
print(keep_freed_memory())
before = mallinfo2()
array = np.ones(5_000_000)
held = mallinfo2()
del array
after = mallinfo2()
print(held.hblkhd - before.hblkhd, after.fordblks - before.fordblks)
"""

# A short alignment's worth of the focus posterior: what it decides and its states' bytes.
POSTERIOR = """
import hashlib
from alignrl.posterior.inference import FamilyPosterior
from alignrl.posterior.models import focus_box
from alignrl.memory import keep_freed_memory
print(keep_freed_memory())
posterior = FamilyPosterior(focus_box(), draws=64, probe_rule="entropy")
posterior.begin()
for setting, width, side in ((0.3, 14.0, 0.0), (0.5, 6.0, 1.0), (0.45, 3.0, 1.0)):
    posterior.observe(setting, width, side)
    print(posterior.decide())
print(hashlib.blake2b(posterior._posterior.tobytes()).hexdigest())
"""


def _run(script: str, **environment: str) -> list[str]:
    result = subprocess.run(
        [sys.executable, "-c", script],
        env={**without_malloc_choices(os.environ), **environment},
        capture_output=True,
        text=True,
        check=True,
        timeout=300,
    )
    return result.stdout.split()


@pytest.mark.skipif(not GLIBC, reason="tunes glibc's allocator only")
def test_a_freed_large_array_stays_in_the_heap_for_the_next() -> None:
    tuned, tuned_mapped, tuned_kept = _run(REUSED)
    system, system_mapped, system_kept = _run(REUSED, ALIGNRL_MALLOC="system")
    assert (tuned, system) == ("True", "False")
    # glibc's default: the array mapped apart and handed back to the kernel when freed
    assert int(system_mapped) >= 40_000_000 and int(system_kept) < 1_000_000
    # tuned: taken from the heap, and kept there once freed
    assert int(tuned_mapped) == 0 and int(tuned_kept) >= 36_000_000


@pytest.mark.skipif(not GLIBC, reason="tunes glibc's allocator only")
def test_the_posterior_computes_the_same_bits_tuned_or_not() -> None:
    tuned, system = _run(POSTERIOR), _run(POSTERIOR, ALIGNRL_MALLOC="system")
    assert tuned[0] == "True" and system[0] == "False"
    assert tuned[1:] == system[1:]


def test_malloc_options_of_the_user_are_left_alone() -> None:
    for environment in ({"MALLOC_TOP_PAD_": "0"}, {"GLIBC_TUNABLES": "glibc.malloc.arena_max=2"},
                        {"ALIGNRL_MALLOC": "System"}):  # fmt: skip
        assert _run(REUSED, **environment)[0] == "False", environment


@pytest.mark.parametrize("value", ["potato", "systme", "0", "x" * 5000])
def test_an_unknown_malloc_choice_is_refused_naming_the_variable_and_the_values(
    monkeypatch: pytest.MonkeyPatch, value: str
) -> None:
    monkeypatch.setenv("ALIGNRL_MALLOC", value)
    with pytest.raises(ValueError, match="ALIGNRL_MALLOC") as caught:
        check_malloc_choice()
    message = str(caught.value)
    assert value[:40] in message and "tuned" in message and "system" in message
    assert len(message) < 300 and "\n" not in message


@pytest.mark.parametrize(
    ("value", "choice"),
    [
        ("system", "system"),
        (" System ", "system"),
        ("SYSTEM", "system"),
        ("tuned", "tuned"),
        ("Tuned", "tuned"),
        ("", "tuned"),
    ],
)
def test_the_malloc_choices_are_read_in_any_case(
    monkeypatch: pytest.MonkeyPatch, value: str, choice: str
) -> None:
    monkeypatch.setenv("ALIGNRL_MALLOC", value)
    assert check_malloc_choice() == choice


def test_keep_freed_memory_raises_for_an_unknown_choice_and_tunes_nothing() -> None:
    script = REUSED.replace("print(keep_freed_memory())", "keep_freed_memory()")
    result = subprocess.run(
        [sys.executable, "-c", script],
        env={**without_malloc_choices(os.environ), "ALIGNRL_MALLOC": "potato"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode != 0
    assert "ValueError: environment variable ALIGNRL_MALLOC='potato'" in result.stderr
