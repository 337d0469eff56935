"""Compiling the loop's kernels before the first dwell."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from estimation.app.config import Config
from estimation.app.dataset import LmsDecoder
from estimation.app.mission import warm
from estimation.app.mission.warm import _AT, _ROOM, _room_scan, warm_up


def test_the_room_scan_lies_on_the_rooms_walls() -> None:
    points = _room_scan()
    assert points.shape == (10_800, 3)
    on_a_face = np.isclose(points, 0.0, atol=1e-9) | np.isclose(points, _ROOM, atol=1e-9)
    assert on_a_face.any(axis=1).all()
    assert (points >= -1e-9).all()
    assert (points <= _ROOM + 1e-9).all()
    assert np.linalg.norm(points - _AT, axis=1).min() > 0.39  # the floor, 0.4 m below


def test_warming_up_decodes_telegrams_and_is_quick_once_compiled(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    made: list[LmsDecoder] = []

    class Kept(LmsDecoder):
        def __init__(self, *args: Any) -> None:
            super().__init__(*args)
            made.append(self)

    monkeypatch.setattr(warm, "LmsDecoder", Kept)
    config = Config()
    warm_up(config)
    assert 0.0 < warm_up(config, {"baud_rate": 500_000}) < 5.0
    assert [d.decoded for d in made] == [4, 4]  # the telegrams it was fed were decoded
    assert [d.undecodable for d in made] == [0, 0]
