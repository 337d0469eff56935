"""The base's reading of robot replies (the network fleet itself is tested with agents in
test_hardware.py and tests/estimation/app/cli/test_live.py)."""

from __future__ import annotations

import math
from typing import Any

import pytest

from estimation.app.live.base import _blocked


def test_a_blocked_point_is_two_finite_numbers() -> None:
    assert _blocked([1.5, -2]) == (1.5, -2.0)
    assert _blocked((0, 0)) == (0.0, 0.0)


@pytest.mark.parametrize(
    "value",
    [None, [], [1.0], [1.0, 2.0, 3.0], ["a", 1.0], [math.nan, 1.0], [1.0, math.inf],
     {"x": 1.0, "y": 2.0}, "1,2", [[1.0], 2.0]],
)  # fmt: skip
def test_anything_else_says_nothing(value: Any) -> None:
    assert _blocked(value) is None
