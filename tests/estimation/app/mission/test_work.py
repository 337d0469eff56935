"""The loop's work per dwell: its parts, and the waits on the worker that are not work."""

from __future__ import annotations

import time

import pytest

from estimation.app.mission import work
from estimation.app.mission.work import PARTS, SLOWEST, WorkClock


def test_work_is_timed_from_a_dwells_end_to_the_next_command_without_the_waits() -> None:
    clock = WorkClock()
    clock.done()  # no dwell yet: nothing timed
    assert clock.work_s == []
    assert not clock.running
    began_all = time.perf_counter()
    clock.start("dwell 1")
    mark = clock.mark()
    time.sleep(0.02)
    mark = clock.part("events", mark)
    began = time.perf_counter()
    time.sleep(0.05)  # waiting on the worker
    clock.exclude(time.perf_counter() - began, waited=True)
    time.sleep(0.01)
    clock.part("isam2", mark)
    clock.done()
    elapsed = time.perf_counter() - began_all
    (work,) = clock.work_s
    parts = clock.parts[0]
    waited = clock.waited_s[0]
    assert waited >= 0.05
    assert parts["events"] >= 0.02
    # the wait is taken out of the part it fell in and out of the dwell's work
    assert 0.01 <= parts["isam2"] < elapsed - waited
    assert parts["fusion"] == 0.0
    assert sum(parts.values()) == pytest.approx(work)
    assert work == pytest.approx(elapsed - waited, abs=0.005)
    summary = clock.summary()
    assert summary["receive_s"]["max"] == 0.0  # nothing received
    waits = summary["localization_waits_s"]
    assert waits["count"] == 1
    assert waits["total"] == waits["max"] == waited
    assert set(summary["work_parts_s"]) == {*PARTS, "slowest_dwells"}
    (listed,) = summary["work_parts_s"]["slowest_dwells"]
    assert listed["dwell"] == "dwell 1"
    assert listed["work"] == pytest.approx(work, abs=1e-4)


def test_the_slowest_dwells_are_listed_slowest_first(monkeypatch: pytest.MonkeyPatch) -> None:
    now = [0.0]
    monkeypatch.setattr(work.time, "perf_counter", lambda: now[0])
    clock = WorkClock()
    for n, seconds in enumerate((0.1, 3.0, 0.2, 1.0, 0.0, 2.0, 0.3)):
        clock.start(f"dwell {n}")
        now[0] += seconds
        clock.done()
    listed = clock.summary()["work_parts_s"]["slowest_dwells"]
    assert [d["dwell"] for d in listed] == ["dwell 1", "dwell 5", "dwell 3", "dwell 6", "dwell 2"]
    assert [d["work"] for d in listed] == pytest.approx([3.0, 2.0, 1.0, 0.3, 0.2])
    assert len(listed) == SLOWEST


def test_time_outside_a_dwells_work_counts_nowhere() -> None:
    clock = WorkClock()
    mark = clock.mark()
    clock.part("fusion", mark)
    clock.exclude(3.0, waited=True, received=True)
    summary = clock.summary()
    assert summary["localization_waits_s"]["count"] == 0
    assert summary["receive_s"]["max"] == 0.0
    assert summary["work_per_dwell_s"] == {"median": 0.0, "p99": 0.0, "max": 0.0}
    assert "slowest_dwells" not in summary["work_parts_s"]
