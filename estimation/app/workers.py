"""Worker processes beside a command (docs/design.md §6, "Worker processes"): spawned, never
forked — the command's process runs GTSAM's and numba's thread pools, which a fork would copy
mid-flight — and gone when their parent is.

:func:`shared_jobs` splits a list of independent jobs between this process and one worker: the
worker takes them from the back, this process from the front, and a job the worker has not yet
started when this process reaches it is done here. ``batch`` and ``isam`` decode large captures
this way (each robot's decoding and sweeps are one job) and draw a result's figures (most of a
figure's time is matplotlib laying out text, which holds the interpreter).
"""

from __future__ import annotations

import collections
import contextlib
import importlib
import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import TypeVar

__all__ = ["shared_jobs", "spawn_worker", "watch_parent", "worker_beside"]

T = TypeVar("T")


def watch_parent(parent_pid: int, poll_s: float = 0.5) -> None:
    """In the worker: exit when the parent process is gone (killed with SIGKILL, a worker
    would otherwise wait for work forever: it holds both ends of the pool's pipes)."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(poll_s)
        os._exit(0)

    threading.Thread(target=watch, name="watch-parent", daemon=True).start()


def _start(parent_pid: int, imports: Sequence[str]) -> None:
    watch_parent(parent_pid)
    for name in imports:
        importlib.import_module(name)


def spawn_worker(imports: Sequence[str] = ()) -> ProcessPoolExecutor | None:
    """One spawned worker process, started now; it first imports the modules ``imports`` (what
    its jobs need, while this process does other work). None when no process can be started
    (the jobs then run here)."""
    try:
        pool = ProcessPoolExecutor(
            1, mp_context=multiprocessing.get_context("spawn"),
            initializer=_start, initargs=(os.getpid(), tuple(imports)),
        )  # fmt: skip
        pool.submit(int)  # the pool starts its process with its first job
    except (OSError, RuntimeError):
        return None
    return pool


@contextlib.contextmanager
def worker_beside(
    imports: Sequence[str], wanted: bool = True
) -> Iterator[ProcessPoolExecutor | None]:
    """:func:`spawn_worker` on entry when ``wanted`` (else None), shut down on exit (after the
    job it is running)."""
    worker = spawn_worker(imports) if wanted else None
    try:
        yield worker
    finally:
        if worker is not None:
            worker.shutdown(wait=True, cancel_futures=True)


def shared_jobs(
    here: Sequence[Callable[[], T]],
    shared: Sequence[Callable[[], T]],
    worker: ProcessPoolExecutor | None,
) -> list[T]:
    """The results of ``here`` (run in this process, first) and then of ``shared`` (picklable
    callables), in order. ``worker`` takes the shared jobs from the back, one at a time, from the
    start; this process takes them from the front once its own are done, until none is left. A
    job's exception is raised here (the first in order). When the worker cannot run (its process
    died or never started), this process runs what is left."""
    pending = collections.deque(range(len(shared)))
    lock = threading.Lock()
    done: dict[int, tuple[bool, object]] = {}

    def take(back: bool) -> int | None:
        with lock:
            if not pending:
                return None
            return pending.pop() if back else pending.popleft()

    def feed() -> None:
        assert worker is not None
        while (k := take(back=True)) is not None:
            try:
                future = worker.submit(shared[k])
                done[k] = (True, future.result())
            except BrokenProcessPool:  # the worker died, or never started: this process runs it
                with lock:
                    pending.append(k)
                return
            except BaseException as exc:  # the job's own error, raised in order below
                done[k] = (False, exc)

    def run_here() -> None:
        while (k := take(back=False)) is not None:
            try:
                done[k] = (True, shared[k]())
            except BaseException as exc:
                done[k] = (False, exc)

    feeder = threading.Thread(target=feed, name="shared-jobs") if worker is not None else None
    if feeder is not None:
        feeder.start()
    finished = False
    try:
        results = [job() for job in here]
        run_here()
        finished = True
    finally:
        if feeder is not None:
            if not finished:
                with lock:
                    pending.clear()  # the worker ends with its current job
            feeder.join()
    run_here()  # what a worker that stopped running handed back
    for k in range(len(shared)):
        ok, value = done[k]
        if not ok:
            raise value  # type: ignore[misc]
        results.append(value)  # type: ignore[arg-type]
    return results
