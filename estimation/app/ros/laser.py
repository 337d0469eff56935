"""``sensor_msgs/LaserScan`` ↔ LMS 200 measured values (docs/ros.md): no I/O.

A LaserScan of coopmap's (``coopmap export DATASET``) holds one decoded scan: ranges in metres
(+inf no return, NaN the other special codes), the flag bits as intensities, the beams counter-
clockwise from −fov/2 to +fov/2 as :func:`~sensors.lms200.protocol.scan.decode_scan` places them.
:func:`telegram_of_scan` turns any LMS 2xx LaserScan back into the ``B0`` telegram the sensor
sent: ranges rounded to the configured unit, intensities above a threshold as reflector bits.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from estimation.app.config import Config, ScannerConfig
from estimation.errors import EstimationError
from sensors.lms200.protocol.plausibility import CM_MAX_RANGE_M, MODE_MAX_RANGE_M, RANGE_MARGIN
from sensors.lms200.protocol.scan import VARIANT_BY_COUNT, Scan, SpecialCode, encode_scan
from sensors.lms200.protocol.telegram import DISTANCE_MASK, FLAG_SHIFT, TURN_S

__all__ = [
    "ANGLE_TOLERANCE_RAD",
    "beam_layout",
    "clockwise",
    "range_limits",
    "scan_angles",
    "scan_fields",
    "scan_timing",
    "telegram_of_scan",
]

#: The angles of a scan may differ this much from the variant's (float32 rounding, drivers).
ANGLE_TOLERANCE_RAD = 1e-4


def scan_angles(config: Config) -> tuple[float, float, float]:
    """(angle_min, angle_max, angle_increment) in radians of the configured variant, counter-
    clockwise from straight ahead, as ``decode_scan`` places the beams."""
    half = math.radians(config.scanner.field_of_view_deg / 2)
    return -half, half, math.radians(config.scanner.angular_resolution_deg)


def scan_fields(scan: Scan) -> tuple[np.ndarray, np.ndarray]:
    """A decoded scan's LaserScan ranges (m; +inf no return, NaN the other special codes) and
    intensities (its flag bits)."""
    ranges = np.where(
        scan.code == SpecialCode.VALID,
        scan.ranges_m,
        np.where(scan.code == SpecialCode.NO_RETURN, np.inf, np.nan),
    )
    return ranges, scan.flags.astype(np.float32)


def scan_timing(config: Config, interval_s: float) -> tuple[float, float]:
    """(time_increment, scan_time) in s: the LMS's internal mirror turns once per ``TURN_S``,
    so one degree takes ``TURN_S`` / 360; scans follow each other every ``interval_s``."""
    return TURN_S * config.scanner.angular_resolution_deg / 360.0, interval_s


def range_limits(config: Config) -> tuple[float, float]:
    """(range_min, range_max) in m: any distance the configured mode and unit can carry."""
    unit_m = 0.001 if config.scanner.unit == "mm" else 0.01
    return 0.0, (DISTANCE_MASK[config.scanner.measuring_mode] - 9) * unit_m


def clockwise(message: Any, fov_deg: int, resolution_deg: float) -> bool | None:
    """Whether the beams of a LaserScan run clockwise (True) or counter-clockwise (False) over
    the variant's field, or None if they are not that variant's beams."""
    if len(message.ranges) != round(fov_deg / resolution_deg) + 1:
        return None
    step, half = math.radians(resolution_deg), math.radians(fov_deg / 2)
    increment, first = float(message.angle_increment), float(message.angle_min)
    if abs(abs(increment) - step) > ANGLE_TOLERANCE_RAD:
        return None
    if increment > 0 and abs(first + half) <= step / 2:
        return False
    if increment < 0 and abs(first - half) <= step / 2:
        return True
    return None


def beam_layout(message: Any, topic: str) -> tuple[int, float, bool]:
    """(field of view °, resolution °, clockwise) of a LaserScan that is an LMS 200 variant;
    ``EstimationError`` naming ``topic`` if it is none."""
    count = len(message.ranges)
    increment = float(message.angle_increment)
    described = (
        f"{topic}: {count} beams from {math.degrees(message.angle_min):.2f}° in steps "
        f"of {math.degrees(increment):.3f}°"
    )
    if count not in VARIANT_BY_COUNT:
        raise EstimationError(
            f"{described}: not an LMS 200 variant (101, 181, 201, 361 or 401 beams)"
        )
    fov, res = VARIANT_BY_COUNT[count]
    flip = clockwise(message, fov, res)
    if flip is None:
        raise EstimationError(
            f"{described}: not the LMS 200's {fov}°/{res:g}° layout "
            f"(−{fov / 2:g}° to +{fov / 2:g}°)"
        )
    return fov, res, flip


def telegram_of_scan(
    message: Any, flip: bool, scanner: ScannerConfig, intensity_threshold: float
) -> tuple[bytes | None, dict[str, int]]:
    """The ``B0`` telegram of a LaserScan (beams clockwise if ``flip``), and the beams that
    carry no range by reason. Ranges are rounded to ``scanner.unit``; non-finite ranges and
    ranges outside the message's [range_min, range_max] or beyond the measuring mode go out as
    "no return". Intensities above ``intensity_threshold`` become the reflector bits (rounded,
    at least 1, at most the mode's flag bits). None: intensities that are not one per range."""
    ranges = np.asarray(message.ranges, dtype=float)
    intensities = np.asarray(message.intensities, dtype=float)
    if len(intensities) not in (0, len(ranges)):
        return None, {}
    if flip:
        ranges, intensities = ranges[::-1], intensities[::-1]
    mm = scanner.unit == "mm"
    longest_m = min(
        float(message.range_max),
        (MODE_MAX_RANGE_M[scanner.measuring_mode] if mm else CM_MAX_RANGE_M) * RANGE_MARGIN,
    )
    finite = np.isfinite(ranges)
    with np.errstate(invalid="ignore"):
        outside = finite & ((ranges < float(message.range_min)) | (ranges > longest_m))
    beams = {
        "NaN or -inf": int(np.count_nonzero(np.isnan(ranges) | (ranges == -np.inf))),
        "+inf (no return)": int(np.count_nonzero(ranges == np.inf)),
        "outside range_min/range_max": int(np.count_nonzero(outside)),
    }
    flags = None
    if len(intensities):
        limit = 0xFFFF >> FLAG_SHIFT[scanner.measuring_mode]
        level = np.clip(np.rint(np.nan_to_num(intensities)), 1, limit)
        flags = np.where(np.nan_to_num(intensities, nan=-np.inf) > intensity_threshold, level, 0)
    telegram = encode_scan(
        np.where(finite & ~outside, ranges, np.nan),
        flags=flags,
        measuring_mode=scanner.measuring_mode,
        unit_mm=mm,
    )
    return telegram, {k: v for k, v in beams.items() if v}
