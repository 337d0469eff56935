"""Synthetic scenes: a large grid rasterised tile by tile is the grid rasterised whole."""

from __future__ import annotations

import numpy as np
import pytest

import estimation.search.scenes as scenes
from estimation.search.scenes import office_floor, rasterise


def test_tiled_rasterisation_equals_the_whole_one(monkeypatch: pytest.MonkeyPatch) -> None:
    scene = office_floor(np.random.default_rng(1), 30.0)
    pose = np.array([0.3, 0.2, 0.4])
    monkeypatch.setattr(scenes, "_TILED_CELLS", 10_000)  # tiles of 100 × 100 cells
    tiled = rasterise(scene, pose, (1.0, 2.0), (230, 170), 0.1)
    monkeypatch.setattr(scenes, "_TILED_CELLS", 10**9)
    whole = rasterise(scene, pose, (1.0, 2.0), (230, 170), 0.1)
    assert np.array_equal(tiled.occupancy, whole.occupancy)
    assert np.array_equal(tiled.known, whole.known)
    assert 0.02 < float((whole.occupancy > 0.5).mean()) < 0.3  # walls and fixtures


def test_office_floor_keeps_room_sized_blocks_on_any_floor() -> None:
    small = office_floor(np.random.default_rng(2), 24.0)
    large = office_floor(np.random.default_rng(2), 96.0)
    # Walls and fixtures grow with the area, not with the side.
    assert 10 < len(large.walls) / len(small.walls) < 25
    assert 8 < len(large.boxes) / len(small.boxes) < 25
    assert np.all(large.walls >= 0.0)
    assert np.all(large.walls <= 96.0)
