"""Trajectory accuracy: ATE, RPE and the Kümmerle relations metric (docs/design.md §12).

Poses are (N, 3) arrays ``x_m, y_m, yaw_rad``; estimate and reference rows correspond (use
:func:`associate` for timestamped trajectories). Nothing here imports gtsam.

* ATE — absolute trajectory error: RMS of the position error and of the heading error, after
  the SE(2) alignment that minimises the position error (Horn/Umeyama without scale), or without
  alignment when both trajectories share a frame.
* RPE — relative pose error over pose pairs ``(i, i + delta)``: RMS of the translation and of the
  rotation of ``(ref_i⁻¹ ref_j)⁻¹ (est_i⁻¹ est_j)``.
* Relations (Kümmerle et al., "On measuring the accuracy of SLAM algorithms", 2009): for each
  ground-truth relation δ*, ``e = δ*⁻¹ ⊕ δ``; mean ± std of ``|trans(e)|`` and ``|rot(e)|``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimation.errors import EstimationError
from sensors.geometry import se2

__all__ = [
    "AteResult",
    "RelationsResult",
    "RpeResult",
    "align_se2",
    "associate",
    "ate",
    "relations_error",
    "rpe",
]


def _poses(name: str, poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise EstimationError(f"{name}: need an (N, 3) array of x, y, yaw, got {poses.shape}")
    if not np.isfinite(poses).all():
        raise EstimationError(f"{name}: poses hold NaN or inf")
    return poses


def _pair(estimate: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    est, ref = _poses("estimate", estimate), _poses("reference", reference)
    if len(est) != len(ref):
        raise EstimationError(
            f"estimate has {len(est)} poses but reference has {len(ref)}; associate them first"
        )
    if len(est) == 0:
        raise EstimationError("no poses to compare")
    return est, ref


def align_se2(estimate: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """T_ref_est (3,) minimising Σ |p_ref − T_ref_est · p_est|² over positions (Umeyama, no scale).

    With fewer than two distinct positions the rotation is taken from the headings instead.
    """
    est, ref = _pair(estimate, reference)
    mu_e, mu_r = est[:, :2].mean(axis=0), ref[:, :2].mean(axis=0)
    de, dr = est[:, :2] - mu_e, ref[:, :2] - mu_r
    cross = (de * dr).sum()  # Σ e·r
    wedge = (de[:, 0] * dr[:, 1] - de[:, 1] * dr[:, 0]).sum()  # Σ e×r
    if math.hypot(cross, wedge) < 1e-12:
        yaw = float(np.angle(np.exp(1j * (ref[:, 2] - est[:, 2])).mean()))
    else:
        yaw = math.atan2(wedge, cross)
    c, s = math.cos(yaw), math.sin(yaw)
    t = mu_r - np.array([c * mu_e[0] - s * mu_e[1], s * mu_e[0] + c * mu_e[1]])
    return np.array([t[0], t[1], yaw])


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error. ``alignment`` is T_ref_est (identity when not aligned)."""

    rmse_m: float
    rmse_rad: float
    max_m: float
    count: int
    alignment: np.ndarray

    @property
    def rmse_deg(self) -> float:
        return math.degrees(self.rmse_rad)


def ate(estimate: np.ndarray, reference: np.ndarray, align: bool = True) -> AteResult:
    """ATE of ``estimate`` against ``reference``; ``align=False`` when frames are shared."""
    est, ref = _pair(estimate, reference)
    T = align_se2(est, ref) if align else np.zeros(3)
    aligned = se2.compose(T, est)
    dist = np.hypot(*(aligned[:, :2] - ref[:, :2]).T)
    dyaw = se2.wrap_angle(aligned[:, 2] - ref[:, 2])
    return AteResult(
        rmse_m=float(np.sqrt(np.mean(dist**2))),
        rmse_rad=float(np.sqrt(np.mean(dyaw**2))),
        max_m=float(dist.max()),
        count=len(est),
        alignment=T,
    )


@dataclass(frozen=True)
class RpeResult:
    """Relative pose error over ``count`` pose pairs ``delta`` apart."""

    rmse_m: float
    rmse_rad: float
    count: int
    delta: int

    @property
    def rmse_deg(self) -> float:
        return math.degrees(self.rmse_rad)


def rpe(estimate: np.ndarray, reference: np.ndarray, delta: int = 1) -> RpeResult:
    """RPE over pairs ``(i, i + delta)``."""
    est, ref = _pair(estimate, reference)
    if delta < 1 or delta >= len(est):
        raise EstimationError(f"RPE delta must be in [1, {len(est) - 1}], got {delta}")
    d_est = se2.between(est[:-delta], est[delta:])
    d_ref = se2.between(ref[:-delta], ref[delta:])
    e = se2.between(d_ref, d_est)
    return RpeResult(
        rmse_m=float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2))),
        rmse_rad=float(np.sqrt(np.mean(e[:, 2] ** 2))),
        count=len(e),
        delta=delta,
    )


def associate(stamps_a: np.ndarray, stamps_b: np.ndarray, max_dt_s: float) -> np.ndarray:
    """For each stamp of ``stamps_b`` the index of the nearest stamp of ``stamps_a``, or −1.

    A match must lie within ``max_dt_s``. ``stamps_a`` need not be sorted; of rows with equal
    stamps the earliest wins, and of two stamps equally near the earlier one.
    """
    a = np.asarray(stamps_a, dtype=float)
    b = np.asarray(stamps_b, dtype=float)
    if a.ndim != 1 or len(a) == 0:
        raise EstimationError("associate: need a non-empty 1-D array of stamps")
    if len(a) == 1:
        index = np.zeros(b.shape, dtype=np.int64)
    else:
        order = np.argsort(a, kind="stable")
        sorted_a = a[order]
        right = np.clip(np.searchsorted(sorted_a, b), 1, len(a) - 1)
        # Several rows may share a stamp: take the first of them (file order).
        left = np.searchsorted(sorted_a, sorted_a[right - 1], side="left")
        right = np.searchsorted(sorted_a, sorted_a[right], side="left")
        pick = np.where(np.abs(sorted_a[left] - b) <= np.abs(sorted_a[right] - b), left, right)
        index = order[pick]
    return np.where(np.abs(a[index] - b) <= max_dt_s, index, -1)


@dataclass(frozen=True)
class RelationsResult:
    """Kümmerle relations metric: mean ± std of translation (m) and rotation (rad) errors."""

    trans_mean_m: float
    trans_std_m: float
    rot_mean_rad: float
    rot_std_rad: float
    count: int
    unmatched: int

    @property
    def rot_mean_deg(self) -> float:
        return math.degrees(self.rot_mean_rad)

    @property
    def rot_std_deg(self) -> float:
        return math.degrees(self.rot_std_rad)


def relations_error(
    stamps_s: np.ndarray,
    poses: np.ndarray,
    relation_stamps: np.ndarray,
    relations: np.ndarray,
    max_dt_s: float = 0.005,
    time_offset_s: float = 0.0,
) -> RelationsResult:
    """Score a timestamped trajectory against ground-truth relations (M, 3) at (M, 2) stamps.

    Each relation's stamps ``t1, t2`` match the trajectory's nearest stamps (plus
    ``time_offset_s``) within ``max_dt_s``; relations that do not match are counted in
    ``unmatched`` and left out.
    """
    poses = _poses("trajectory", poses)
    stamps = np.asarray(stamps_s, dtype=float) + time_offset_s
    relations = _poses("relations", relations)
    relation_stamps = np.asarray(relation_stamps, dtype=float).reshape(-1, 2)
    if len(relation_stamps) != len(relations):
        raise EstimationError(
            f"{len(relation_stamps)} relation stamp pairs for {len(relations)} relations"
        )
    i1 = associate(stamps, relation_stamps[:, 0], max_dt_s)
    i2 = associate(stamps, relation_stamps[:, 1], max_dt_s)
    ok = (i1 >= 0) & (i2 >= 0)
    if not ok.any():
        raise EstimationError(
            f"no relation matches the trajectory's stamps within {max_dt_s} s (check the offset)"
        )
    delta = se2.between(poses[i1[ok]], poses[i2[ok]])
    e = se2.between(relations[ok], delta)
    trans = np.hypot(e[:, 0], e[:, 1])
    rot = np.abs(e[:, 2])
    return RelationsResult(
        trans_mean_m=float(trans.mean()),
        trans_std_m=float(trans.std()),
        rot_mean_rad=float(rot.mean()),
        rot_std_rad=float(rot.std()),
        count=int(ok.sum()),
        unmatched=int((~ok).sum()),
    )
