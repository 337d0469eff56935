"""Jobs shared between this process and a spawned worker: every result once, in order, the
errors raised here, and the rest run here when the worker cannot."""

from __future__ import annotations

import functools
import os
import signal
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor

import pytest

from estimation.app.workers import shared_jobs, worker_beside


def _where(k: int, seconds: float = 0.0) -> tuple[int, int]:
    time.sleep(seconds)
    return k, os.getpid()


def _fails(k: int) -> int:
    raise ValueError(f"job {k} failed")


@pytest.fixture
def worker() -> Iterator[ProcessPoolExecutor]:
    """A worker that has started (both sides take jobs from the first), shut down after."""
    with worker_beside([]) as started:
        assert started is not None
        started.submit(int).result(timeout=60)
        yield started


def test_jobs_are_shared_and_come_back_in_order(worker: ProcessPoolExecutor) -> None:
    here = [functools.partial(_where, -1, 0.3)]
    shared = [functools.partial(_where, k, 0.15) for k in range(8)]
    results = shared_jobs(here, shared, worker)
    assert [k for k, _ in results] == [-1, *range(8)]
    pids = [pid for _, pid in results]
    assert pids[0] == os.getpid()
    theirs = [k for k, pid in results if pid != os.getpid()]
    ours = [k for k, pid in results[1:] if pid == os.getpid()]
    # The worker takes from the back, this process from the front, and each some.
    assert theirs
    assert ours
    assert max(ours) < min(theirs)
    assert theirs[-1] == 7


def test_without_a_worker_every_job_runs_here() -> None:
    results = shared_jobs([], [functools.partial(_where, k) for k in range(3)], None)
    assert results == [(k, os.getpid()) for k in range(3)]
    assert shared_jobs([], [], None) == []


@pytest.mark.parametrize("failing", [0, 5])
def test_the_first_failing_job_in_order_raises_here(
    worker: ProcessPoolExecutor, failing: int
) -> None:
    shared = [functools.partial(_where, k, 0.05) for k in range(6)]
    shared[failing] = functools.partial(_fails, failing)  # 0 runs here, 5 in the worker
    with pytest.raises(ValueError, match=f"job {failing} failed"):
        shared_jobs([], shared, worker)


def test_a_job_failing_here_stops_the_worker_after_its_current_job(
    worker: ProcessPoolExecutor,
) -> None:
    shared = [functools.partial(_where, k, 0.2) for k in range(6)]
    started = time.perf_counter()
    with pytest.raises(ValueError, match="job -1 failed"):
        shared_jobs([functools.partial(_fails, -1)], shared, worker)
    assert time.perf_counter() - started < 1.0  # not all six jobs of 0.2 s


def test_a_dead_worker_leaves_its_jobs_to_this_process(worker: ProcessPoolExecutor) -> None:
    for pid in list(worker._processes):  # killed as by the OOM killer
        os.kill(pid, signal.SIGKILL)
    time.sleep(0.5)
    results = shared_jobs([], [functools.partial(_where, k) for k in range(4)], worker)
    assert results == [(k, os.getpid()) for k in range(4)]


def test_a_worker_that_cannot_start_leaves_every_job_here() -> None:
    with worker_beside(["coopmap_no_such_module"]) as broken:
        assert broken is not None
        results = shared_jobs([], [functools.partial(_where, k) for k in range(3)], broken)
    assert results == [(k, os.getpid()) for k in range(3)]


def test_a_worker_not_wanted_is_none() -> None:
    with worker_beside(["estimation.app.dataset"], wanted=False) as none:
        assert none is None
