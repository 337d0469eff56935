"""Compiling the mission loop's kernels before the mission starts.

numba compiles a kernel the first time it runs (and caches it on disk for the next process).
Without a cache, the loop's first dwell compiled the LMS decoding, the fusion and the
planner's kernels: 39 s of work on the 2-core machine (generated building 5), all before the
robots' first command. The loop runs them once on a few telegrams and a small room of its own
before the first dwell instead.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from estimation.app.config import Config
from estimation.app.dataset import LmsDecoder
from estimation.app.mission.view import MapView
from estimation.app.rig import scan_limits
from mapping.fusion import Scan, fuse_scans
from mapping.grid import GridParams
from sensors.lms200.protocol.scan import encode_scan

__all__ = ["warm_up"]

_ROOM = np.array([4.0, 3.0, 2.5])
_AT = np.array([2.0, 1.5, 0.4])


def warm_up(config: Config, header: dict[str, Any] | None = None) -> float:
    """Run the LMS decoding (set up as for a robot whose capture ``header`` is given), the
    estimated map's fusion and the planner's kernels once, on a few telegrams and a room seen
    from its middle; returns the seconds it took."""
    began = time.perf_counter()
    decoder = LmsDecoder(config.scanner.measuring_mode, scan_limits(config), header)
    scanner = config.scanner
    ranges = np.full(round(scanner.field_of_view_deg / scanner.angular_resolution_deg) + 1, 2.0)
    decoder.feed_chunks([
        (0.01 * n, encode_scan(ranges, measuring_mode=scanner.measuring_mode, scan_index=n,
                               telegram_index=n))
        for n in range(4)
    ])  # fmt: skip
    params = GridParams(**config.grid.model_dump())
    pose = np.eye(4)
    pose[:3, 3] = _AT
    grid = fuse_scans([Scan(_room_scan() - _AT)], pose[None], params)
    grid.copy()
    robots = np.array([_AT[:2], _AT[:2] + np.array([1.0, 0.5])])
    view = MapView(grid, config, stood_xy=robots, robots_xy=robots)
    a, c = np.array([*robots[0], 0.0]), np.array([*robots[1], math.pi])
    view.geometry.sees_beacon(a, c)  # the 3D line of sight and the walls beside robots
    view.coverage.gain(a)
    view.distances_from([robots[0]])
    return time.perf_counter() - began


def _room_scan() -> np.ndarray:
    """Where rays from ``_AT`` in every direction (±80° in elevation) meet the room's walls."""
    azimuth, elevation = np.meshgrid(
        np.linspace(-np.pi, np.pi, 180, endpoint=False), np.radians(np.linspace(-80, 80, 60))
    )
    d = np.stack(
        [
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
        ],
        axis=-1,
    ).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (_ROOM - _AT) / d, np.where(d < 0, -_AT / d, np.inf))
    return _AT + d * t.min(axis=1, keepdims=True)
