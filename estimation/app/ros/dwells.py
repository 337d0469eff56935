"""Dwells and moves from odometry alone: where all robots stood still, and how they moved
between (docs/ros.md, "Importing a bag"); pure functions on odometry arrays.

An odometry log is stamps (N,) in seconds and planar poses (N, 3) ``x_m, y_m, yaw_rad`` in the
robot's odometry frame. A robot stands still between two consecutive samples when it moved and
turned less than the :class:`DwellRule`'s speed and turn rate allow over their interval.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimation.app.config import ConfigError
from sensors.geometry.se2 import wrap_angle

__all__ = ["DwellRule", "find_dwells", "moves_and_dwells"]

Odometry = dict[str, tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class DwellRule:
    """When the robots stand still for a dwell (docs/ros.md): between consecutive odometry
    samples, each robot moves less than ``still_speed_m_s`` and turns less than
    ``still_turn_rate_deg_s``, all of them together for at least ``min_dwell_s`` (None: half
    the configured mirror period, the shortest stop that can hold one sweep)."""

    still_speed_m_s: float = 0.01
    still_turn_rate_deg_s: float = 0.5
    min_dwell_s: float | None = None

    def __post_init__(self) -> None:
        for name in ("still_speed_m_s", "still_turn_rate_deg_s", "min_dwell_s"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ConfigError(f"dwell detection: {name} must be > 0, got {value!r}")


def _runs(flags: np.ndarray, stamps_s: np.ndarray) -> list[tuple[float, float]]:
    """Time spans of the runs of True in ``flags`` (one flag per interval between samples)."""
    edges = np.diff(np.concatenate([[0], flags.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(float(stamps_s[a]), float(stamps_s[b])) for a, b in zip(starts, ends, strict=True)]


def _moving(stamps_s: np.ndarray, poses: np.ndarray, rule: DwellRule) -> np.ndarray:
    """Per interval between consecutive samples: whether the robot moved or turned faster than
    the rule's thresholds."""
    dt = np.diff(stamps_s)
    step = np.hypot(np.diff(poses[:, 0]), np.diff(poses[:, 1]))
    turn = np.abs(wrap_angle(np.diff(poses[:, 2])))
    return np.asarray(
        (step > rule.still_speed_m_s * dt) | (turn > math.radians(rule.still_turn_rate_deg_s) * dt)
    )


def find_dwells(
    odometry: Odometry, rule: DwellRule, min_dwell_s: float
) -> list[tuple[float, float]]:
    """The spans (start_s, end_s) in which every robot's odometry (stamps (N,), poses (N, 3))
    stands still by ``rule`` for at least ``min_dwell_s``, in time order."""
    common: list[tuple[float, float]] | None = None
    for stamps, poses in odometry.values():
        still = _runs(~_moving(stamps, poses, rule), stamps)
        if common is None:
            common = still
            continue
        merged, i, j = [], 0, 0
        while i < len(common) and j < len(still):
            lo, hi = max(common[i][0], still[j][0]), min(common[i][1], still[j][1])
            if lo < hi:
                merged.append((lo, hi))
            i, j = (i + 1, j) if common[i][1] < still[j][1] else (i, j + 1)
        common = merged
    return [(a, b) for a, b in common or [] if b - a >= min_dwell_s]


def moves_and_dwells(
    odometry: Odometry,
    dwells: list[tuple[float, float]],
    rule: DwellRule,
    reference: str | None = None,
    mapper: str | None = None,
) -> list[dict[str, Any]]:
    """The event log (docs/dataset.md) of robots that stop at ``dwells``: a ``start`` per robot,
    one ``move`` per robot that moved between two dwells (from its first departure to its last
    arrival), a ``dwell`` per span with every robot's pose index; in time order."""
    robots = list(odometry)
    events: list[dict[str, Any]] = [
        {"t_s": float(stamps[0]), "event": "start", "robot": r, "index": 0}
        for r, (stamps, _) in odometry.items()
    ]
    moves: dict[tuple[int, str], tuple[float, float]] = {}
    dwell_ends = np.array([end for _, end in dwells])
    for robot, (stamps, poses) in odometry.items():
        for start, end in _runs(_moving(stamps, poses, rule), stamps):
            gap = int(np.searchsorted(dwell_ends, start, side="right"))
            first, last = moves.get((gap, robot), (start, end))
            moves[(gap, robot)] = (min(first, start), max(last, end))
    index = dict.fromkeys(robots, 0)
    moved_first = any(gap == 0 for gap, _ in moves)
    for gap in range(len(dwells) + 1):
        for robot in robots:
            if (gap, robot) in moves:
                start, end = moves[(gap, robot)]
                events.append(
                    {
                        "t_s": end,
                        "event": "move",
                        "robot": robot,
                        "from_index": index[robot],
                        "to_index": index[robot] + 1,
                        "start_s": start,
                    }
                )
                index[robot] += 1
        if gap < len(dwells):
            t_s, end_s = dwells[gap]
            dwell: dict[str, Any] = {
                "t_s": t_s,
                "event": "dwell",
                "end_s": end_s,
                "poses": dict(index),
                "phase": "start" if gap == 0 and not moved_first else "mapping",
            }
            if reference is not None:
                dwell["reference"] = reference
            if mapper is not None:
                dwell["mapper"] = mapper
            dwell["step"] = gap - 1
            events.append(dwell)
    priority = {"start": 0, "move": 1, "dwell": 2}
    return sorted(events, key=lambda e: (e["t_s"], priority[e["event"]]))
