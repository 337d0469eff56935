"""Calibration of the beacon's height and offset from mutual observations (docs/calibration.md).

**Height.** The reflective band of a beacon is ``length_m`` tall and centred on its height. The
flagged returns on a detected beacon's axis span that band (the scan elevations sample it in
steps), so the midpoint of their vertical extent is the band's centre; the median over many
detections is robust to a clipped band (:func:`beacon_centre_height`).

**Offset.** Robot A sees robot C's beacon at range and bearing (a, α) in A's scanner frame, and
C sees A's at (b, β) (docs/design.md §4). Both measure the distance between the two beacons, s1
from A and s2 from C; with the beacon d straight ahead of each scanner origin::

    s1² = a² + d² − 2ad cos α,   s2² = b² + d² − 2bd cos β

and s1 = s2 gives, per observation, d = (a² − b²) / (2 (a cos α − b cos β)).
:func:`estimate_beacon_offset` combines the observations by weighted least squares on
f = a² − b² − 2d (a cos α − b cos β) (weights from the range and bearing noise, propagated),
re-weighted with Huber's function to resist outliers. Observations with a cos α ≈ b cos β (the
robots see each other symmetrically: equal ranges and equal bearings) carry no information
about d and are skipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sensors.errors import SensorError

__all__ = [
    "OffsetEstimate",
    "beacon_centre_height",
    "beacon_separations",
    "estimate_beacon_offset",
]

#: Huber's constant, in standard deviations.
HUBER_K = 2.0


def beacon_centre_height(
    points_scanner: np.ndarray,
    reflector: np.ndarray,
    axis_xy: np.ndarray,
    *,
    radius_m: float,
    band_center_m: float,
    band_half_m: float,
) -> float | None:
    """Height (scanner frame, m) of the centre of a beacon's reflective band, or None.

    The flagged returns within ``radius_m`` (plus 5 cm) of the beacon's axis ``axis_xy`` and
    within ``band_half_m`` of ``band_center_m`` are the band's; the result is the midpoint of
    their vertical extent. None when fewer than three returns are there.
    """
    points = np.asarray(points_scanner, dtype=float)[np.asarray(reflector, dtype=bool)]
    points = points[np.isfinite(points).all(axis=1)]
    near = np.hypot(points[:, 0] - axis_xy[0], points[:, 1] - axis_xy[1]) <= radius_m + 0.05
    near &= np.abs(points[:, 2] - band_center_m) <= band_half_m
    z = points[near, 2]
    if len(z) < 3:
        return None
    return float(0.5 * (z.min() + z.max()))


def beacon_separations(
    a_m: np.ndarray, alpha_rad: np.ndarray, b_m: np.ndarray, beta_rad: np.ndarray, offset_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """s1 (from A) and s2 (from C): the beacon-to-beacon distance measured both ways (m)."""
    s1 = np.sqrt(np.maximum(a_m**2 + offset_m**2 - 2 * a_m * offset_m * np.cos(alpha_rad), 0.0))
    s2 = np.sqrt(np.maximum(b_m**2 + offset_m**2 - 2 * b_m * offset_m * np.cos(beta_rad), 0.0))
    return s1, s2


@dataclass(frozen=True)
class OffsetEstimate:
    """The beacon offset from the mutual observations, and what it rests on."""

    offset_m: float
    sigma_m: float  # standard error
    used: int
    skipped_degenerate: int
    downweighted: int  # observations Huber's function down-weighted (outliers)
    separation_rms_before_m: float  # RMS of s1 − s2 over the used observations, start offset
    separation_rms_after_m: float


def _sigma_f(a: np.ndarray, alpha: np.ndarray, b: np.ndarray, beta: np.ndarray, d: float,
             range_sigma_m: float, bearing_sigma_rad: float) -> np.ndarray:  # fmt: skip
    """Standard deviation of f = a² − b² − 2d (a cos α − b cos β), first order."""
    da = 2 * a - 2 * d * np.cos(alpha)
    db = 2 * b - 2 * d * np.cos(beta)
    dalpha = 2 * a * d * np.sin(alpha)
    dbeta = 2 * b * d * np.sin(beta)
    variance = (da**2 + db**2) * range_sigma_m**2 + (dalpha**2 + dbeta**2) * bearing_sigma_rad**2
    return np.sqrt(np.maximum(variance, 1e-18))


def estimate_beacon_offset(
    a_m: np.ndarray,
    alpha_rad: np.ndarray,
    b_m: np.ndarray,
    beta_rad: np.ndarray,
    *,
    start_offset_m: float,
    range_sigma_m: float,
    bearing_sigma_rad: float,
    min_asymmetry_m: float = 0.05,
) -> OffsetEstimate:
    """The beacon offset d (m) that makes s1 = s2 over the mutual observations (a, α, b, β).

    Observations with |a cos α − b cos β| < ``min_asymmetry_m`` are degenerate and skipped.
    Raises :class:`SensorError` when nothing is left, or on non-finite input.
    """
    a, alpha, b, beta = (
        np.asarray(v, dtype=float).ravel() for v in (a_m, alpha_rad, b_m, beta_rad)
    )
    if not (a.shape == alpha.shape == b.shape == beta.shape):
        raise SensorError("a, α, b and β must have one value per observation")
    if len(a) == 0:
        raise SensorError("no mutual observations to calibrate the beacon offset from")
    if not np.isfinite(np.concatenate([a, alpha, b, beta])).all():
        raise SensorError("a mutual observation holds a NaN or infinite value")
    if (a <= 0).any() or (b <= 0).any():
        raise SensorError("a mutual observation has a range <= 0")
    asymmetry = a * np.cos(alpha) - b * np.cos(beta)
    usable = np.abs(asymmetry) >= min_asymmetry_m
    if not usable.any():
        raise SensorError(
            f"all {len(a)} mutual observations are degenerate (a cos α ≈ b cos β within "
            f"{min_asymmetry_m * 100:g} cm: the robots saw each other symmetrically); record "
            "observations in which the two bearings differ"
        )
    a, alpha, b, beta, asymmetry = (v[usable] for v in (a, alpha, b, beta, asymmetry))
    x = 2 * asymmetry
    y = a**2 - b**2
    d = start_offset_m
    weights = np.ones(len(a))
    scale = 1.0
    for _ in range(30):
        sigma = _sigma_f(a, alpha, b, beta, d, range_sigma_m, bearing_sigma_rad)
        normalised = (y - d * x) / sigma
        if len(a) >= 4:
            scale = max(1.4826 * float(np.median(np.abs(normalised))), 1e-9)
        weights = np.minimum(1.0, HUBER_K / np.maximum(np.abs(normalised) / scale, 1e-12))
        w = weights / sigma**2
        new = float(np.sum(w * x * y) / np.sum(w * x * x))
        if abs(new - d) < 1e-9:
            d = new
            break
        d = new
    if not math.isfinite(d):
        raise SensorError("the beacon offset fit diverged")
    sigma = _sigma_f(a, alpha, b, beta, d, range_sigma_m, bearing_sigma_rad)
    w = weights / sigma**2
    residual = (y - d * x) / sigma
    dof = max(len(a) - 1, 1)
    factor = math.sqrt(max(float(np.sum(weights * residual**2)) / dof, 1e-12))
    before = np.subtract(*beacon_separations(a, alpha, b, beta, start_offset_m))
    after = np.subtract(*beacon_separations(a, alpha, b, beta, d))
    return OffsetEstimate(
        offset_m=d,
        sigma_m=float(factor / math.sqrt(float(np.sum(w * x * x)))),
        used=len(a),
        skipped_degenerate=int(np.count_nonzero(~usable)),
        downweighted=int(np.count_nonzero(weights < 1.0)),
        separation_rms_before_m=float(np.sqrt(np.mean(before**2))),
        separation_rms_after_m=float(np.sqrt(np.mean(after**2))),
    )
