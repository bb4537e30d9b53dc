"""The posterior's workspace: what is made once per process (the first draw of columns, a
prior, kept read-only and shared), the (K, Z, N) buffers a posterior keeps its state in, and
this thread's scratch buffers that each step overwrites. Nothing here changes a number the
posterior computes: the same operations, into memory that is already there.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

__all__ = ["CACHED", "CACHED_BYTES", "PosteriorBuffers", "read_only", "remembered", "scratch"]

CACHED = 3  # first draws and priors kept per process (the least recently used go first)
CACHED_BYTES = 1 << 26  # nor one larger than this (a calibration's search: made per search)
_scratch = threading.local()  # per thread: one flat buffer per name
_cache_lock = threading.Lock()


class PosteriorBuffers(NamedTuple):
    """The (K, Z, N) arrays a posterior keeps its state in (FamilyPosterior, made per
    instance: a copy makes its own): two posteriors, the present one and the next, and where
    its readings' scale is unknown the scale's two sums (ScaleSums)."""

    posteriors: tuple[np.ndarray, np.ndarray]
    sums: tuple[np.ndarray, np.ndarray] | None

    @classmethod
    def make(cls, shape: tuple[int, ...], scale_free: bool) -> PosteriorBuffers:
        sums = (np.empty(shape), np.empty(shape)) if scale_free else None
        return cls((np.empty(shape), np.empty(shape)), sums)

    def other(self, posterior: np.ndarray) -> np.ndarray:
        """The posterior buffer that is not `posterior`."""
        first, second = self.posteriors
        return second if posterior is first else first

    def holding(self, posterior: np.ndarray) -> np.ndarray:
        """The first posterior buffer, holding `posterior`'s numbers."""
        np.copyto(self.posteriors[0], posterior)
        return self.posteriors[0]

    def holding_sums(self, *sums: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """The sums' buffers, holding `sums` (arrays, or one number each)."""
        for buffer, value in zip(self.sums, sums, strict=True):
            np.copyto(buffer, value)
        return self.sums


def remembered(cache: OrderedDict, key: tuple, make: Callable[[], tuple]) -> tuple:
    """`cache[key]`, made by `make()` where missing and kept unless its arrays hold more than
    CACHED_BYTES (CACHED kept, the least recently used dropped first)."""
    with _cache_lock:
        if key in cache:
            cache.move_to_end(key)
            return cache[key]
    made = make()
    if sum(value.nbytes for value in made if isinstance(value, np.ndarray)) <= CACHED_BYTES:
        with _cache_lock:
            cache[key] = made
            while len(cache) > CACHED:
                cache.popitem(last=False)
    return made


def read_only(*arrays: np.ndarray) -> None:
    """Mark `arrays` read-only: made once, shared by every posterior alike."""
    for array in arrays:
        array.setflags(write=False)


def scratch(name: str, shape: tuple[int, ...], dtype: type = np.float64) -> np.ndarray:
    """This thread's buffer `name` of `shape`, its numbers what the last use left: a view of
    one flat array per name, made again only where a larger one is asked."""
    buffers = _scratch.__dict__.setdefault("buffers", {})
    size = math.prod(shape)
    flat = buffers.get((name, dtype))
    if flat is None or flat.size < size:
        flat = buffers[(name, dtype)] = np.empty(max(size, 1), dtype)
    return flat[:size].reshape(shape)
