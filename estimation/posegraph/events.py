"""What reaches the estimator: a stream of small, immutable events (docs/design.md §8).

Robots produce odometry, mutual beacon observations and global-localization results; whether
they come from a recorded dataset, a simulation or robots over a network, the estimator sees
only these four event types, in order. A pose is named by its robot (one letter) and its index.
Poses are ``(x_m, y_m, yaw_rad)`` of the robot frame; deltas are in the previous pose's frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimation.errors import EstimationError
from estimation.posepdf import PosePdf

__all__ = ["Event", "Localize", "Move", "Observe", "PoseRef", "Start", "checked_covariance"]

PoseRef = tuple[str, int]
"""(robot letter, pose index)."""


@dataclass(frozen=True)
class Start:
    """The gauge: ``robot``'s pose ``index`` is at ``pose`` in the map frame (a prior)."""

    robot: str
    index: int
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Move:
    """``robot`` moved from its latest pose to pose ``index``; ``delta`` is T_prev_new
    (x_m, y_m, yaw_rad) measured by odometry. ``motion`` (m driven, rad turned along the way,
    from the odometry's samples) sets the step's uncertainty; without it the step is taken to
    be the straight move ``delta``."""

    robot: str
    index: int
    delta: tuple[float, float, float]
    motion: tuple[float, float] | None = None


@dataclass(frozen=True)
class Observe:
    """A mutual observation: ``observer`` (A) sees the beacon of ``observed`` (C) at
    ``(a_m, alpha_rad)`` in A's scanner frame, and C sees A's beacon at ``(b_m, beta_rad)``."""

    observer: PoseRef
    observed: PoseRef
    a_m: float
    alpha_rad: float
    b_m: float
    beta_rad: float


@dataclass(frozen=True)
class Localize:
    """A global-localization result: ``pdf`` over the pose of ``(robot, index)`` in the map frame
    (``reference`` None: matched against a fixed prior map) or in the frame of the earlier
    station ``reference`` (matched against the part of this mission's map it built).
    ``peak_radius`` (m, rad) is the neighbourhood of the peak whose probability the factor's
    covariance is fitted to; None: the configured ``search.peak_radius_*``. ``pose`` is the
    search's refined best pose (``SearchResult.pose``: the score maximised on the interpolated
    map), the factor's measurement; None: the PDF's own best pose (``PosePdf.best_pose``, a
    quadratic through the lattice peak). ``covariance`` (3, 3), of (x, y, yaw) in the reference
    frame, replaces the one fitted to the PDF when the measurement came from elsewhere (a
    registration of the stations' points, ``estimation.search.registration``)."""

    robot: str
    index: int
    pdf: PosePdf
    reference: PoseRef | None = None
    peak_radius: tuple[float, float] | None = None
    pose: tuple[float, float, float] | None = None
    covariance: tuple[tuple[float, ...], ...] | None = None


Event = Start | Move | Observe | Localize


def checked_covariance(covariance: object, what: str) -> np.ndarray:
    """``covariance`` as a (3, 3) float array, or ``EstimationError`` naming ``what`` unless it
    is finite, symmetric and positive definite."""
    try:
        matrix = np.asarray(covariance, dtype=float)
    except (TypeError, ValueError):
        message = f"{what} must be a 3x3 matrix of numbers, got {covariance!r}"
        raise EstimationError(message) from None
    ok = matrix.shape == (3, 3) and bool(np.isfinite(matrix).all())
    ok = ok and bool(np.allclose(matrix, matrix.T, rtol=1e-9, atol=1e-15))
    if ok:
        try:
            np.linalg.cholesky(matrix)
        except np.linalg.LinAlgError:
            ok = False
    if not ok:
        raise EstimationError(f"{what} must be a finite symmetric positive definite 3x3 matrix, "
                              f"got {np.array2string(matrix, precision=4)}")  # fmt: skip
    return matrix
