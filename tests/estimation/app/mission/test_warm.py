"""Compiling the loop's kernels before the first dwell."""

from __future__ import annotations

import numpy as np

from estimation.app.config import Config
from estimation.app.dataset import LmsDecoder
from estimation.app.rig import scan_limits
from estimation.app.mission.warm import _AT, _ROOM, _room_scan, warm_up


def test_the_room_scan_lies_on_the_rooms_walls() -> None:
    points = _room_scan()
    assert points.shape == (10_800, 3)
    on_a_face = np.isclose(points, 0.0, atol=1e-9) | np.isclose(points, _ROOM, atol=1e-9)
    assert on_a_face.any(axis=1).all()
    assert (points >= -1e-9).all()
    assert (points <= _ROOM + 1e-9).all()
    assert np.linalg.norm(points - _AT, axis=1).min() > 0.39  # the floor, 0.4 m below


def test_warming_up_runs_and_is_quick_once_compiled() -> None:
    config = Config()
    warm_up(config)
    assert 0.0 < warm_up(config) < 5.0
    decoder = LmsDecoder(config.scanner.measuring_mode, scan_limits(config))
    assert 0.0 < warm_up(config, decoder) < 5.0
    assert decoder.decoded == 4  # the telegrams it was fed were decoded
