"""The loop's estimated map: the sweeps fused in order at poses within the re-fusion limits of
their estimates, fused again from the settled base when a recent estimate moves and from
scratch when a settled one does."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from estimation.app.config import Config
from estimation.app.mission.estimated_map import EstimatedMap
from estimation.app.rig import T_robot_scanner
from estimation.posegraph.keys import pose_key
from mapping.fusion import Scan, fuse_scans
from mapping.grid import OccupancyGrid
from sensors.geometry.frames import pose2_matrix
from tests.mapping.conftest import room_scan

CONFIG = Config()
ROOM = (6.0, 4.0, 2.5)


def sweep(n: int) -> Any:
    """Robot a's sweep n: a room seen from a place of its own, in the scanner's frame."""
    place = np.array([1.0 + 0.35 * n, 1.0 + 0.15 * (n % 5), 0.4])
    points = room_scan(place, ROOM, azimuth_steps=90, elevation_steps=30) - place
    return SimpleNamespace(robot="a", index=n, dwell=n, points_scanner=points)


def fused_afresh(map_: EstimatedMap) -> OccupancyGrid:
    """The map's sweeps fused one after the other at the poses it says it holds them at."""
    mount = T_robot_scanner(CONFIG)
    return fuse_scans(
        [Scan(s.points_scanner) for s in map_.order],
        np.stack([pose2_matrix(*map_.fused[id(s)]) @ mount for s in map_.order]),
        map_.params,
    )


def assert_same(a: OccupancyGrid, b: OccupancyGrid) -> None:
    cells_a, values_a = a.cells()
    cells_b, values_b = b.cells()
    order_a, order_b = np.lexsort(cells_a.T), np.lexsort(cells_b.T)
    np.testing.assert_array_equal(cells_a[order_a], cells_b[order_b])
    np.testing.assert_array_equal(values_a[order_a], values_b[order_b])


def test_the_map_is_its_sweeps_fused_in_order_within_the_limits_of_their_estimates() -> None:
    """Twelve sweeps arrive one by one; now a recent estimate moves, now a settled one, now one
    by less than the limits. After every update the map is its sweeps fused afresh."""
    sweeps = [sweep(n) for n in range(12)]
    estimate: dict[int, np.ndarray] = {}
    map_ = EstimatedMap(CONFIG, window=2)
    moves = {  # at sweep n: which sweep's estimate moves, and by how much
        5: (4, [0.05, 0.0, 0.0]),  # recent (window 2: five sweeps in, three settled)
        7: (1, [0.0, 0.04, 0.0]),  # settled long ago
        9: (8, [0.01, 0.01, math.radians(0.3)]),  # within the limits
        10: (9, [0.0, 0.0, math.radians(1.0)]),  # recent, turned
    }
    counts = []
    for n in range(len(sweeps)):
        estimate[pose_key("a", n)] = np.array([0.3 * n, 0.1 * n, 0.05 * n])
        if n in moves:
            which, by = moves[n]
            estimate[pose_key("a", which)] = estimate[pose_key("a", which)] + by
        map_.update(sweeps[: n + 1], estimate)
        assert [x.index for x in map_.order] == list(range(n + 1))
        for x in map_.order:
            held, now = map_.fused[id(x)], estimate[pose_key("a", x.index)]
            assert math.hypot(*(held[:2] - now[:2])) <= 0.03
            assert abs(held[2] - now[2]) <= math.radians(0.5)
        assert_same(map_.grid, fused_afresh(map_))
        assert len(map_.order) - map_.settled <= 2 * map_.window
        counts.append((map_.refusions, map_.from_scratch, map_.settled))
    assert counts[4] == (0, 0, 3)  # more than twice the window: the older sweeps settled
    assert counts[5] == (1, 0, 3)  # fused again from the base
    assert counts[7] == (2, 1, 6)  # from scratch, then settled again
    assert counts[9] == counts[8]  # nothing fused again
    assert counts[10] == (3, 1, 9)


def test_a_sweep_whose_pose_left_the_estimate_leaves_the_map() -> None:
    sweeps = [sweep(n) for n in range(4)]
    estimate = {pose_key("a", n): np.array([0.3 * n, 0.0, 0.0]) for n in range(4)}
    map_ = EstimatedMap(CONFIG, window=8)
    map_.update(sweeps, estimate)
    del estimate[pose_key("a", 2)]
    map_.update(sweeps, estimate)
    assert [s.index for s in map_.order] == [0, 1, 3]
    assert map_.refusions == 1
    assert_same(map_.grid, fused_afresh(map_))


def test_the_window_must_hold_a_sweep() -> None:
    with pytest.raises(ValueError, match="window"):
        EstimatedMap(CONFIG, window=0)
