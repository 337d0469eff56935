"""The global grid as the mission loop estimates it: the sweeps fused at their estimated poses,
fused again from scratch when an estimate it rests on moved."""

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


class EstimatedMap:
    """The global grid as the loop estimates it, from the sweeps at their estimated poses."""

    def __init__(self, config: Config) -> None:
        self.params = GridParams(**config.grid.model_dump())
        self.mount = T_robot_scanner(config)
        self.grid = OccupancyGrid(self.params)
        self.fused: dict[int, np.ndarray] = {}  # id(sweep) → the pose it was fused at
        self.refusions = 0

    def update(self, sweeps: list[Sweep], estimate: dict[int, np.ndarray]) -> None:
        usable = [s for s in sweeps if pose_key(s.robot, s.index) in estimate]
        moved = any(
            id(s) in self.fused and _moved(self.fused[id(s)], estimate[pose_key(s.robot, s.index)])
            for s in usable
        )
        if moved:
            self.grid = OccupancyGrid(self.params)
            self.fused = {}
            self.refusions += 1
        new = [s for s in usable if id(s) not in self.fused]
        if not new:
            return
        poses = [estimate[pose_key(s.robot, s.index)] for s in new]
        fuse_scans(
            [MapScan(s.scan.points_scanner) for s in new],
            np.stack([pose2_matrix(*p) @ self.mount for p in poses]),
            self.params,
            self.grid,
        )
        for sweep, pose in zip(new, poses, strict=True):
            self.fused[id(sweep)] = pose.copy()


def _moved(a: np.ndarray, b: np.ndarray) -> bool:
    return (
        math.hypot(a[0] - b[0], a[1] - b[1]) > _REFUSE_M
        or abs(math.remainder(a[2] - b[2], 2 * math.pi)) > _REFUSE_RAD
    )
