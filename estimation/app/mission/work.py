"""The mission loop's work per dwell: from the end of a dwell to the robots' next command, in
parts (events, iSAM2, map fusion; the rest is choosing the goal), without the time spent
waiting on the concurrent global localization, which runs during the robots' next sweep, and
without the time the robots' recordings take to reach the loop (over the network, or in a
simulated mission the simulator making them)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

__all__ = ["PARTS", "WorkClock"]

#: The parts of a dwell's work: receiving and decoding the recordings and detecting beacons
#: into events, the iSAM2 update with the estimate, fusing the sweeps at the estimate, and the
#: rest, mostly choosing the goal.
PARTS = ("events", "isam2", "fusion", "goal")
#: How many of the slowest dwells the report lists with their parts.
SLOWEST = 5


class WorkClock:
    """Times the loop's work per dwell (``work_s``), its parts (``parts``), its waits on the
    concurrent localization (``waited_s``) and on the recordings (``received_s``), not work."""

    def __init__(self) -> None:
        self.work_s: list[float] = []
        self.parts: list[dict[str, float]] = []
        self.waited_s: list[float] = []
        self.received_s: list[float] = []
        self.labels: list[str] = []  # per dwell: which dwell it was
        self._since: float | None = None
        self._excluded = 0.0  # all time excluded so far
        self._part = dict.fromkeys(PARTS, 0.0)
        self._label = ""

    @property
    def running(self) -> bool:
        """Whether a dwell's work is being timed."""
        return self._since is not None

    def start(self, label: str = "") -> None:
        """A dwell (``label``: which) has ended: its work begins."""
        self._since = time.perf_counter()
        self._part = dict.fromkeys(PARTS, 0.0)
        self._label = label

    def exclude(self, seconds: float, waited: bool = False, received: bool = False) -> None:
        """Time that is not the dwell's work: a wait on the worker (``waited``), the robots'
        recordings reaching the loop (``received``), the live view."""
        if self._since is not None:
            self._since += seconds
            self._excluded += seconds
            if waited:
                self.waited_s.append(seconds)
            if received:
                self.received_s.append(seconds)

    def mark(self) -> tuple[float, float]:
        """Now, for :meth:`part`."""
        return time.perf_counter(), self._excluded

    def part(self, name: str, since: tuple[float, float]) -> tuple[float, float]:
        """Count the work from ``since`` (a :meth:`mark`) to now, without the time excluded in
        between, to part ``name``; returns a mark of now."""
        now = self.mark()
        if self._since is not None:
            self._part[name] += (now[0] - since[0]) - (now[1] - since[1])
        return now

    def done(self) -> None:
        """The robots get their next command: the dwell's work ends."""
        if self._since is not None:
            work = time.perf_counter() - self._since
            self._part["goal"] = max(0.0, work - sum(self._part.values()))
            self.work_s.append(work)
            self.parts.append(self._part)
            self.labels.append(self._label)
            self._since = None

    def summary(self) -> dict[str, Any]:
        """``report.json``'s figures: work per dwell (median, p99, max), each part's median,
        p99 and max, the slowest dwells with their parts, and the waits."""
        work = np.array(self.work_s) if self.work_s else np.zeros(1)
        parts: dict[str, Any] = {}
        for name in PARTS:
            values = np.array([p[name] for p in self.parts]) if self.parts else np.zeros(1)
            parts[name] = _spread(values)
        if self.parts:
            parts["slowest_dwells"] = [
                {"dwell": self.labels[i], "work": round(float(work[i]), 4),
                 **{k: round(v, 4) for k, v in self.parts[i].items()}}
                for i in np.argsort(-work, kind="stable")[:SLOWEST]
            ]  # fmt: skip
        waits = {"count": len(self.waited_s), "total": float(sum(self.waited_s)),
                 "max": float(max(self.waited_s, default=0.0))}  # fmt: skip
        received = np.array(self.received_s) if self.received_s else np.zeros(1)
        return {"work_per_dwell_s": _spread(work), "work_parts_s": parts,
                "localization_waits_s": waits, "receive_s": _spread(received)}  # fmt: skip


def _spread(values: np.ndarray) -> dict[str, float]:
    return {"median": float(np.median(values)), "p99": float(np.percentile(values, 99)),
            "max": float(values.max())}  # fmt: skip
