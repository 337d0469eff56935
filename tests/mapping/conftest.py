"""Shared helpers: the shared real data, analytic scans of a box room, a reference fusion."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.kernels.traversal import ray_cells
from tests.paths import DATA

FR079 = DATA / "octomap_fr079"

requires_fr079 = pytest.mark.skipif(
    not FR079.is_dir(), reason="../shared/data/octomap_fr079 is absent"
)


def room_scan(
    sensor: np.ndarray,
    size_m: tuple[float, float, float] = (4.0, 3.0, 2.5),
    azimuth_steps: int = 180,
    elevation_steps: int = 60,
) -> np.ndarray:
    """End points of a 360° × (−80…+80°) fan of rays from ``sensor`` to the walls, floor and
    ceiling of the box [0, size_m] (analytic ray casting)."""
    az = np.linspace(-np.pi, np.pi, azimuth_steps, endpoint=False)
    el = np.radians(np.linspace(-80.0, 80.0, elevation_steps))
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    upper = np.asarray(size_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (upper - sensor) / d, np.where(d < 0, -sensor / d, np.inf))
    return np.asarray(sensor + d * t.min(axis=1, keepdims=True))


def reference_fusion(
    points: np.ndarray, sensor: np.ndarray, resolution_m: float, free_ends: np.ndarray = ()
) -> tuple[set[tuple[int, ...]], set[tuple[int, ...]]]:
    """OctoMap's insertPointCloud semantics with Python sets: (occupied cells, free cells)."""
    occupied = {tuple(c) for c in np.floor(np.asarray(points) / resolution_m).astype(int)}
    free: set[tuple[int, ...]] = set()
    start = np.asarray(sensor) / resolution_m
    for end in [*list(points), *list(free_ends)]:
        free.update(map(tuple, ray_cells(start, np.asarray(end) / resolution_m, False)))
    return occupied, free - occupied
