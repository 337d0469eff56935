"""Mirror calibration on synthetic sweeps of a box room, traced through the mirror geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensors.errors import SensorError
from sensors.scan3d.mirror import MirrorEstimate, MirrorGeometry
from sensors.scan3d.mirror_calibration import (
    MirrorFitSettings,
    SweepSamples,
    edge_on_motor_phase,
    fit_mirror,
)

HEIGHT_M = 0.45
TRUE_D = 0.1
SETTINGS = MirrorFitSettings(scanner_height_m=HEIGHT_M, scanner_x_m=0.1, exclude_radius_m=0.4)


def room_sweep(
    rng: np.random.Generator,
    *,
    yaw_rad: float,
    elevations_deg: np.ndarray,
    walls: bool = True,
    d: float = TRUE_D,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(range, bearing, true elevation) of the beams that hit a 7 m × 6 m room, 3 m high,
    around a scanner 0.45 m above the floor (range noise 5 mm)."""
    theta, phi = np.meshgrid(np.radians(np.arange(-50.0, 51.0)), np.radians(elevations_deg))
    theta, phi = theta.ravel(), phi.ravel()
    origin = np.column_stack([np.full_like(theta, d), d * np.tan(theta), np.zeros_like(theta)])
    direction = np.column_stack(
        [np.cos(phi) * np.cos(theta), np.sin(theta), np.sin(phi) * np.cos(theta)]
    )
    planes = [((0.0, 0.0, 1.0), -HEIGHT_M)]
    if walls:
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        planes += [((0.0, 0.0, 1.0), 3.0 - HEIGHT_M)]
        planes += [
            ((c, s, 0.0), 4.0),
            ((-s, c, 0.0), 3.0),
            ((s, -c, 0.0), 3.0),
            ((-c, -s, 0.0), 3.0),
        ]
    path = np.full(len(theta), np.inf)
    for normal, offset in planes:
        n = np.asarray(normal)
        along = direction @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (offset - origin @ n) / along
        path = np.where((np.abs(along) > 1e-9) & (t > 0) & (t < path), t, path)
    hit = np.isfinite(path)
    r = d / np.cos(theta) + path + rng.normal(0.0, 0.005, len(theta))
    return r[hit], theta[hit], phi[hit]


#: One scan every 1.44° of elevation (12.5 scans/s), outside the ±6° edge-on blind band.
ELEVATIONS_DEG = np.concatenate([np.arange(-88.0, -6.0, 1.44), np.arange(6.5, 88.0, 1.44)])


def room_sweeps(
    correction_rad: float, *, walls: bool = True, elevations_deg: np.ndarray = ELEVATIONS_DEG
) -> list[SweepSamples]:
    """Three sweeps at different headings, assembled with elevations off by −correction."""
    rng = np.random.default_rng(1)
    sweeps = []
    for yaw in (0.3, 1.4, 2.6):
        r, b, e = room_sweep(rng, yaw_rad=yaw, elevations_deg=elevations_deg, walls=walls)
        sweeps.append(SweepSamples(r, b, e - correction_rad))
    return sweeps


def test_fit_recovers_axis_offset_and_elevation_correction() -> None:
    truth = math.radians(2.5)
    fit = fit_mirror(room_sweeps(truth), TRUE_D + 0.03, SETTINGS)
    assert fit.axis_offset_m == pytest.approx(TRUE_D, abs=3e-4)
    assert math.degrees(fit.elevation_correction_rad) == pytest.approx(2.5, abs=0.02)
    assert fit.rms_after_m < 0.006  # the 5 mm range noise
    assert fit.rms_before_m > 0.03
    assert fit.planes["floor"] == 1
    assert fit.planes["vertical"] >= 3  # walls in view of each sweep
    assert fit.planes["horizontal"] >= 3  # the ceiling of each sweep
    assert fit.sweeps == 3
    assert fit.warnings == ()
    assert fit.sigma_axis_offset_m < 1e-4


def test_the_start_shift_enters_only_the_residual_before() -> None:
    shifted = [SweepSamples(s.range_m, s.bearing_rad, s.elevation_rad, start_shift_rad=0.05)
               for s in room_sweeps(0.0)]  # fmt: skip
    plain = fit_mirror(room_sweeps(0.0), TRUE_D, SETTINGS)
    fit = fit_mirror(shifted, TRUE_D, SETTINGS)
    assert fit.axis_offset_m == pytest.approx(plain.axis_offset_m, abs=1e-4)
    assert fit.elevation_correction_rad == pytest.approx(plain.elevation_correction_rad, abs=1e-4)
    assert plain.rms_before_m < 0.006
    assert fit.rms_before_m > 0.03


def test_a_floor_seen_at_one_elevation_is_reported_as_ill_conditioned() -> None:
    sweeps = room_sweeps(0.0, walls=False, elevations_deg=np.arange(-31.0, -29.0, 0.5))
    fit = fit_mirror(sweeps, TRUE_D, SETTINGS)
    assert any("poorly" in w or "confounded" in w for w in fit.warnings), fit.warnings


def first_sweep_cut(count: int) -> list[SweepSamples]:
    s = room_sweeps(0.0)[0]
    return [SweepSamples(s.range_m[:count], s.bearing_rad[:count], s.elevation_rad[:count])]


def mismatched() -> list[SweepSamples]:
    s = room_sweeps(0.0)[0]
    return [SweepSamples(s.range_m, s.bearing_rad[:-1], s.elevation_rad)]


@pytest.mark.parametrize(
    ("sweeps", "axis_offset_m", "height_m", "message"),
    [
        ([], TRUE_D, HEIGHT_M, r"no sweeps to calibrate the mirror from"),
        (None, float("nan"), HEIGHT_M, r"starting axis offset must be positive, got nan"),
        (None, TRUE_D, float("nan"), r"scanner height must be positive, got nan"),
        (None, TRUE_D, 5.0, r"no returns on the floor at 5 m below the scanner"),
        (first_sweep_cut(50), TRUE_D, HEIGHT_M, r"only \d+ usable returns in 1 sweeps: too few"),
        (
            mismatched(),
            TRUE_D,
            HEIGHT_M,
            r"sweep 0: range, bearing and elevation must be equal-length",
        ),
    ],
)
def test_fit_errors_name_the_problem(
    sweeps: list[SweepSamples] | None, axis_offset_m: float, height_m: float, message: str
) -> None:
    settings = MirrorFitSettings(scanner_height_m=height_m)
    with pytest.raises(SensorError, match=message):
        fit_mirror(room_sweeps(0.0) if sweeps is None else sweeps, axis_offset_m, settings)


def estimate_at(phase_deg: float, *, fine: bool = False) -> MirrorEstimate:
    geometry = MirrorGeometry(axis_offset_m=0.1, gear_ratio=80.0, nominal_motor_period_s=0.5)
    return MirrorEstimate(
        motor_period_s=0.5, motor_phase_time_s=3.0, edge_on_time_s=3.0 + 0.5 * (7 + phase_deg / 360),
        fine_phase=fine, edges_used=20, edges_rejected=0, geometry=geometry,
    )  # fmt: skip


def test_edge_on_phase_is_a_circular_mean() -> None:
    found = edge_on_motor_phase([estimate_at(p) for p in (350.0, 356.0, 4.0, 10.0)])
    assert math.degrees(found.phase_rad) == pytest.approx(0.0, abs=1e-6) or math.degrees(
        found.phase_rad
    ) == pytest.approx(360.0, abs=1e-6)
    assert math.degrees(found.spread_rad) == pytest.approx(7.4, abs=0.3)
    assert found.dwells == 4
    assert math.degrees(edge_on_motor_phase([estimate_at(40.0)] * 3).phase_rad) == pytest.approx(
        40.0
    )


def test_edge_on_phase_errors() -> None:
    with pytest.raises(SensorError, match="no dwell with arm edges and an edge-on signature"):
        edge_on_motor_phase([])
    with pytest.raises(SensorError, match="needs coarse mirror estimates"):
        edge_on_motor_phase([estimate_at(10.0, fine=True)])
    with pytest.raises(SensorError, match="disagree on the motor phase"):
        edge_on_motor_phase([estimate_at(0.0), estimate_at(180.0)])
