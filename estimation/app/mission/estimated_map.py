"""The global grid as the mission loop estimates it: the sweeps fused at their estimated poses,
fused again when an estimate they rest on moved.

The sweeps are fused in the order they came, each at the pose it had then. A settled base
grid holds all but the latest sweeps (at most twice ``window``); the map is a copy of the base
with the latest fused on top. When an estimate moves, it is nearly always a recent sweep's
(the mutual observation or the station link of the station being mapped): then only the
sweeps after the base are fused again, on a fresh copy of it. Only when a settled sweep moved
(a loop closure) is everything fused again from scratch. Either way, the map is exactly the
sweeps fused one after the other, each within ``_REFUSE_M`` and ``_REFUSE_RAD`` of its
estimate.
"""

from __future__ import annotations

import math

import numpy as np

from estimation.app.config import Config
from estimation.app.dataset import Sweep
from estimation.app.rig import T_robot_scanner
from estimation.posegraph.keys import pose_key
from mapping.fusion import Scan as MapScan
from mapping.fusion import fuse_scans
from mapping.grid import GridParams, OccupancyGrid
from sensors.geometry.frames import pose2_matrix

__all__ = ["EstimatedMap"]

#: A fused sweep whose pose estimate moved more than this (m, rad) gets the map re-fused.
_REFUSE_M, _REFUSE_RAD = 0.03, math.radians(0.5)
#: Sweeps kept out of the base: a move among them re-fuses these alone.
WINDOW = 32


class EstimatedMap:
    """The global grid as the loop estimates it, from the sweeps at their estimated poses."""

    def __init__(self, config: Config, window: int = WINDOW) -> None:
        if window < 1:
            raise ValueError(f"EstimatedMap: window must be at least 1, got {window}")
        self.params = GridParams(**config.grid.model_dump())
        self.mount = T_robot_scanner(config)
        self.window = window
        self.base = OccupancyGrid(self.params)  # the first ``settled`` sweeps of ``order``
        self.grid = OccupancyGrid(self.params)  # every sweep of ``order``
        self.order: list[Sweep] = []  # the sweeps fused, in the order they were
        self.settled = 0
        self.fused: dict[int, np.ndarray] = {}  # id(sweep) → the pose it was fused at
        self.refusions = 0  # times the map was fused again, from the base or from scratch
        self.from_scratch = 0

    def update(self, sweeps: list[Sweep], estimate: dict[int, np.ndarray]) -> None:
        usable = [s for s in sweeps if pose_key(s.robot, s.index) in estimate]
        ids = {id(s) for s in usable}
        stale = next(
            (
                n
                for n, s in enumerate(self.order)
                if id(s) not in ids or _moved(self.fused[id(s)], _pose(s, estimate))
            ),
            None,
        )
        new = [s for s in usable if id(s) not in self.fused]
        if stale is None:
            recent = new
        else:
            self.refusions += 1
            if stale < self.settled:  # a settled sweep moved: start again
                self.from_scratch += 1
                every = [s for s in self.order if id(s) in ids] + new
                self.fused = {}
                # The older sweeps go straight into a new base: each is fused once.
                head = every[: len(every) - self.window] if len(every) > 2 * self.window else []
                self.base = OccupancyGrid(self.params)
                self._fuse(self.base, head, [_pose(s, estimate) for s in head])
                self.order, self.settled = head, len(head)
                recent = every[len(head) :]
            else:
                recent = [s for s in self.order[self.settled :] if id(s) in ids] + new
                for sweep in self.order[self.settled :]:
                    del self.fused[id(sweep)]
                self.order = self.order[: self.settled]
            self.grid = self.base.copy() if self.settled else OccupancyGrid(self.params)
        self._fuse(self.grid, recent, [_pose(s, estimate) for s in recent])
        self.order += recent
        if len(self.order) - self.settled > 2 * self.window:
            # The older half of the recent sweeps settles into the base, at the poses the
            # map holds them at: base + the rest is still the map.
            upto = len(self.order) - self.window
            settling = self.order[self.settled : upto]
            self._fuse(self.base, settling, [self.fused[id(s)] for s in settling])
            self.settled = upto

    def _fuse(self, grid: OccupancyGrid, sweeps: list[Sweep], poses: list[np.ndarray]) -> None:
        if not sweeps:
            return
        fuse_scans(
            [MapScan(s.points_scanner) for s in sweeps],
            np.stack([pose2_matrix(*p) @ self.mount for p in poses]),
            self.params,
            grid,
        )
        for sweep, pose in zip(sweeps, poses, strict=True):
            self.fused[id(sweep)] = np.array(pose, dtype=float)


def _pose(sweep: Sweep, estimate: dict[int, np.ndarray]) -> np.ndarray:
    return estimate[pose_key(sweep.robot, sweep.index)]


def _moved(a: np.ndarray, b: np.ndarray) -> bool:
    return (
        math.hypot(a[0] - b[0], a[1] - b[1]) > _REFUSE_M
        or abs(math.remainder(a[2] - b[2], 2 * math.pi)) > _REFUSE_RAD
    )
