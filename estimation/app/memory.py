"""The process's heap under glibc's malloc: handing back what a stage freed, and how many
arenas the threads may spread it over.

glibc keeps freed memory in its arenas, one per thread that allocated while another held the
first, up to eight per core. A stage's working set then stays in the process's RSS while the
next stage adds its own, and the search threads' arenas each keep their own high-water mark
(office_loop's ``batch``: 544 MB peak with the default, 517 MB with two arenas). Elsewhere
than glibc both steps are skipped, never an error.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os

__all__ = ["give_back_memory", "limit_arenas"]

M_ARENA_MAX = -8  # glibc's mallopt parameter for the most arenas


@functools.cache
def _libc() -> ctypes.CDLL | None:
    """The C library, or None where it cannot be loaded."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or None)
    except OSError:
        return None


def give_back_memory() -> None:
    """Return the heap the last stage freed to the system (glibc's ``malloc_trim``)."""
    trim = getattr(_libc(), "malloc_trim", None)
    if trim is not None:
        trim(0)


def limit_arenas(count: int) -> bool:
    """Let malloc keep at most ``count`` arenas, unless the user set ``MALLOC_ARENA_MAX``
    (glibc reads it at start). Takes effect for arenas made afterwards, so it is called before
    any thread starts. True if the limit was set."""
    if count < 1:
        raise ValueError(f"limit_arenas: count must be >= 1, got {count}")
    if "MALLOC_ARENA_MAX" in os.environ:
        return False
    mallopt = getattr(_libc(), "mallopt", None)
    return mallopt is not None and bool(mallopt(M_ARENA_MAX, count))
