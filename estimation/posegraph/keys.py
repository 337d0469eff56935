"""The one place where pose-graph keys are made (docs/design.md §5): ``gtsam.symbol(robot, index)``.

A robot is named by one lowercase letter (``"a"``, ``"b"``, …); its poses are numbered from 0.
"""

from __future__ import annotations

import gtsam

from estimation.errors import EstimationError

__all__ = ["check_robot", "key_label", "pose_key", "split_key"]

_MAX_INDEX = (1 << 56) - 1


def check_robot(robot: str) -> str:
    """``robot`` if it is one lowercase ASCII letter, else an ``EstimationError``."""
    if not (isinstance(robot, str) and len(robot) == 1 and "a" <= robot <= "z"):
        raise EstimationError(f"robot name must be one lowercase letter a-z, got {robot!r}")
    return robot


def pose_key(robot: str, index: int) -> int:
    """The gtsam key of pose ``index`` of ``robot``."""
    check_robot(robot)
    if not 0 <= int(index) <= _MAX_INDEX or int(index) != index:
        raise EstimationError(f"pose index must be an integer in [0, 2^56), got {index!r}")
    return int(gtsam.symbol(robot, int(index)))


def split_key(key: int) -> tuple[str, int]:
    """(robot, index) of a key made by :func:`pose_key`."""
    symbol = gtsam.Symbol(key)
    robot = chr(symbol.chr())
    check_robot(robot)
    return robot, int(symbol.index())


def key_label(key: int) -> str:
    """A short human label of a pose key, e.g. ``"b17"``."""
    robot, index = split_key(key)
    return f"{robot}{index}"
