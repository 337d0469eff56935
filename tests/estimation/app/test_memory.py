"""The heap helpers: glibc's malloc_trim and mallopt where they exist, nothing elsewhere."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from estimation.app import memory

GLIBC = platform.libc_ver()[0] == "glibc"


@pytest.fixture
def no_libc(monkeypatch: pytest.MonkeyPatch):
    """A C library that cannot be loaded."""
    memory._libc.cache_clear()
    monkeypatch.setattr(memory.ctypes, "CDLL", lambda *_: (_ for _ in ()).throw(OSError("none")))
    yield
    memory._libc.cache_clear()


def test_freed_heap_is_given_back_where_the_c_library_can() -> None:
    """glibc keeps a stage's freed heap in the process; ``batch`` hands it back between stages."""
    memory._libc.cache_clear()
    assert hasattr(memory._libc(), "malloc_trim") == GLIBC
    memory.give_back_memory()


def test_without_the_c_library_both_steps_are_skipped(no_libc) -> None:
    assert memory._libc() is None
    memory.give_back_memory()  # skipped, not an error
    assert memory.limit_arenas(2) is False


def test_a_user_set_arena_limit_is_left_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
    assert memory.limit_arenas(2) is False


@pytest.mark.parametrize("count", [0, -1])
def test_an_arena_count_below_one_is_refused(count: int) -> None:
    with pytest.raises(ValueError, match="count must be >= 1"):
        memory.limit_arenas(count)


def test_threads_share_the_arenas_allowed() -> None:
    """In a fresh process limited to one arena, eight threads that allocate at once leave one
    arena (malloc_info lists each arena as a <heap nr=...>); without the limit, more. Without
    glibc there is no limit to set, and ``limit_arenas`` says so."""
    if not GLIBC:
        assert memory.limit_arenas(1) is False
        return
    code = """
import ctypes, ctypes.util, os, sys, threading
from estimation.app.memory import limit_arenas
if sys.argv[1] == "1":
    assert limit_arenas(1)
libc = ctypes.CDLL(ctypes.util.find_library("c"))
barrier = threading.Barrier(8)
def work():
    barrier.wait()
    kept = [bytearray(4096) for _ in range(2000)]
threads = [threading.Thread(target=work) for _ in range(8)]
[t.start() for t in threads]; [t.join() for t in threads]
libc.fdopen.restype = ctypes.c_void_p
read, write = os.pipe()
stream = libc.fdopen(write, b"w")
libc.malloc_info(0, ctypes.c_void_p(stream)); libc.fclose(ctypes.c_void_p(stream))
print(os.read(read, 1 << 20).decode().count("<heap nr="))
"""
    counts = {}
    for limited in ("1", "0"):
        env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
        out = subprocess.run([sys.executable, "-c", code, limited], capture_output=True,
                             text=True, timeout=60, env=env, check=True)  # fmt: skip
        counts[limited] = int(out.stdout.split()[-1])
    assert counts["1"] == 1
    assert counts["0"] > 1
