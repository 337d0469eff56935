"""The leapfrog planner's geometry: what a scan from a pose would cover, and the mapper poses
around a reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimation.app.config import Config
from estimation.app.sim.planning import BeaconGeometry, CoverageModel, mapper_candidates
from sensors.sim.planner import FreeSpace


def coverage(seed: int) -> CoverageModel:
    """A 6 m × 4 m floor with scattered opaque cells, part of it covered already."""
    rng = np.random.default_rng(seed)
    shape = (40, 60)
    space = FreeSpace(np.ones(shape, bool), np.ones(shape), np.array([-1.0, -0.5]), 0.1)
    return CoverageModel(space, rng.random(shape) < 0.8, rng.random(shape) < 0.3,
                         rng.random(shape) < 0.04)  # fmt: skip


def visible_reference(model: CoverageModel, x: float, y: float, yaw: float) -> np.ndarray:
    """What a scan sees, with numpy: rays at 101 bearings sampled every half cell, each up to
    its first opaque cell or the map's edge."""
    res = model.space.resolution_m
    angles = yaw + np.linspace(-math.radians(50.0), math.radians(50.0), 101)
    steps = np.arange(0.3, 7.0, res / 2)
    px = x + np.outer(np.cos(angles), steps)
    py = y + np.outer(np.sin(angles), steps)
    cols = np.floor((px - model.space.lower_xy[0]) / res).astype(int)
    rows = np.floor((py - model.space.lower_xy[1]) / res).astype(int)
    h, w = model.opaque.shape
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    rows_c, cols_c = np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)
    blocked = ~inside | model.opaque[rows_c, cols_c]
    open_ray = np.cumsum(blocked, axis=1) == 0
    seen = np.zeros_like(model.opaque)
    seen[rows_c[open_ray], cols_c[open_ray]] = True
    return seen & model.target


@pytest.mark.parametrize("seed", range(4))
def test_the_gain_of_a_pose_counts_the_uncovered_cells_it_sees(seed: int) -> None:
    model = coverage(seed)
    rng = np.random.default_rng(100 + seed)
    gains = []
    for _ in range(40):
        pose = rng.uniform((-1.5, -1.0, -math.pi), (5.5, 4.0, math.pi))
        seen = visible_reference(model, *pose)
        np.testing.assert_array_equal(model.visible(*pose), seen)
        expected = int(np.count_nonzero(seen & ~model.covered))
        assert model.gain(pose) == expected
        gains.append(expected)
    assert max(gains) > 50  # the poses see something
    assert min(gains) == 0 or len(set(gains)) > 5
    # Covering what a pose sees leaves nothing for it to gain.
    model.add(pose)
    assert model.gain(pose) == 0


def test_mapper_candidates_put_their_beacon_in_the_band_and_face_the_reference() -> None:
    config = Config()
    geometry = BeaconGeometry(config, line_clear=lambda a, b: True)
    reference = np.array([1.0, -2.0, 0.7])
    candidates = mapper_candidates(reference, geometry, (1.5, 3.5))
    assert len(candidates) == 100
    origin = geometry.scanner(reference)
    for pose in candidates:
        distance = float(np.linalg.norm(geometry.beacon(pose) - origin))
        assert 1.5 - 1e-9 <= distance <= 3.5 + 1e-9
        to_ref = geometry.beacon(reference) - geometry.scanner(pose)
        bearing = math.remainder(math.atan2(to_ref[1], to_ref[0]) - pose[2], 2 * math.pi)
        assert abs(abs(bearing) - math.radians(25)) < math.radians(0.5)
