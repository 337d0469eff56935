"""Beacon detection on simulated 3D scans: accuracy over 1–8 m, distractors, blind wedge."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sensors.geometry.frames import scanner_pose_matrix
from sensors.lms200.protocol.scan import decode_scan
from sensors.lms200.protocol.stream import StreamParser, Telegram
from sensors.scan3d.beacon import _fit_circle_lstsq, detect_beacons, fit_circle_fixed_radius
from sensors.scan3d.mirror import MirrorGeometry, assemble_sweeps, estimate_mirror, scan_times
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.sensing import (
    RobotBody,
    SimulatedScanner,
    scan_stream,
    telegram_times,
    world_with_robots,
)
from sensors.sim.world import World, world_from_mapping

GEOMETRY = MirrorGeometry(axis_offset_m=0.1, gear_ratio=80.0, nominal_motor_period_s=0.5)
BODY = RobotBody()
DETECT = {
    "radius_m": BODY.beacon_radius_m,
    "center_height_m": BODY.beacon_height_m - 0.45,
    "length_m": BODY.beacon_length_m,
    "height_tolerance_m": 0.15,
    "radius_tolerance_m": 0.03,
    "min_returns": 3,
    "max_range_m": 9.0,
    "blind_wedge_rad": math.radians(20),
}
SCANNER_A = (2.0, 7.0, 0.0)


def hall(*boxes: dict) -> World:  # type: ignore[type-arg]
    room = {"name": "h", "footprint": [[0, 0], [20, 0], [20, 14], [0, 14]], "ceiling_m": 3.0}
    return world_from_mapping({"name": "hall", "rooms": [room], "boxes": list(boxes)})


def observe(world: World, separation_m: float, bearing_rad: float, heading_rad: float, seed: int):  # type: ignore[no-untyped-def]
    """Robot B placed so that its beacon is at (separation, bearing) from A's scanner."""
    T = scanner_pose_matrix(*SCANNER_A, BODY.scanner_x_m, 0.45)
    bx = T[0, 3] + separation_m * math.cos(bearing_rad)
    by = T[1, 3] + separation_m * math.sin(bearing_rad)
    ahead = BODY.scanner_x_m + BODY.beacon_offset_m
    robot_b = (bx - ahead * math.cos(heading_rad), by - ahead * math.sin(heading_rad), heading_rad)
    scene = RaycastScene(build_mesh(world_with_robots(world, {"b": robot_b}, BODY)))
    scanner = SimulatedScanner(GEOMETRY, motor_period_s=0.503, arm_phase_time_s=0.1,
                               edge_on_turn=20, seed=seed)  # fmt: skip
    truth = scanner.scan(
        scene, T, telegram_times(0, 20.0, 38400, 101, 1.0), np.random.default_rng(seed)
    )
    parser = StreamParser()
    scans = [
        decode_scan(e, 1)
        for s, c in scan_stream(truth)
        for e in parser.feed(c, s)
        if isinstance(e, Telegram)
    ]
    times = scan_times(scans)
    sweeps = assemble_sweeps(scans, times, estimate_mirror(scans, times, GEOMETRY))
    assert len(sweeps) == 1
    return detect_beacons(sweeps[0].points_scanner, sweeps[0].reflector, **DETECT)


def test_beacon_range_and_bearing_over_1_to_8_m() -> None:
    rng = np.random.default_rng(1)
    post = {"name": "post", "center": [6.0, 9.0], "size": [0.1, 0.1], "z_m": [0, 1.5],
            "retroreflective": True}  # fmt: skip
    world = hall(post)
    range_errors, bearing_errors, missed = [], [], []
    for k, separation in enumerate(np.linspace(1.0, 8.0, 10)):
        bearing = math.radians(rng.choice([-1, 1]) * rng.uniform(15, 35))
        detections, rejections = observe(
            world, separation, bearing, rng.uniform(-math.pi, math.pi), k
        )
        assert len(detections) <= 1
        if not detections:
            # At 8 m the 0.2 m beacon spans 1.4° (one or two beams) on about three scan lines.
            missed.append(separation)
            continue
        range_errors.append(abs(detections[0].range_m - separation))
        bearing_errors.append(abs(math.degrees(detections[0].bearing_rad - bearing)))
        # The reflective post, when seen, is rejected with its reason.
        assert all("post or sign" in r.reason or "beacon height" in r.reason for r in rejections)
    assert len(missed) <= 1
    assert all(m > 7.0 for m in missed)
    assert np.median(range_errors) < 0.03
    assert np.median(bearing_errors) < 0.5
    assert max(range_errors) < 0.05


def test_reflective_post_and_sign_are_not_beacons() -> None:
    post = {
        "name": "post",
        "center": [5.0, 7.5],
        "size": [0.1, 0.1],
        "z_m": [0, 2.5],
        "retroreflective": True,
    }
    sign = {
        "name": "sign",
        "center": [8.0, 9.0],
        "size": [0.05, 0.8],
        "z_m": [1.45, 1.75],
        "retroreflective": True,
    }
    detections, rejections = observe(hall(post, sign), 3.0, math.radians(-30), 0.0, 3)
    assert len(detections) == 1  # only robot b's beacon
    assert detections[0].range_m == pytest.approx(3.0, abs=0.03)
    reasons = " ".join(r.reason for r in rejections)
    assert "a reflective post or sign" in reasons
    assert "wider than the beacon" in reasons


def test_beacons_in_the_forward_blind_wedge_are_not_reported() -> None:
    detections, rejections = observe(hall(), 3.0, math.radians(4.0), 1.0, 5)
    assert detections == []
    assert any("inside the forward blind wedge" in r.reason for r in rejections)


def test_circle_fit_recovers_the_axis() -> None:
    rng = np.random.default_rng(0)
    center, radius = np.array([3.0, 1.0]), 0.1
    near = math.atan2(-center[1], -center[0])  # the side facing the scanner
    angles = near + rng.uniform(-1.0, 1.0, 30)
    xy = (
        center
        + radius * np.column_stack([np.cos(angles), np.sin(angles)])
        + rng.normal(0, 0.003, (30, 2))
    )
    fitted, residual = fit_circle_fixed_radius(xy, radius)
    np.testing.assert_allclose(fitted, center, atol=0.005)
    assert residual < 0.005


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 80), noise=st.floats(0.0, 0.02))
def test_the_circle_fit_takes_the_least_squares_steps(seed: int, n: int, noise: float) -> None:
    """The fit's steps from their 2 × 2 normal equations are the least-squares steps (the
    returns of an arc seen from the scanner, up to 2 cm off it): the same centre to 1e-12 m
    (2e-15 m at most in 20,000 random arcs). Two returns fit two circles about equally well,
    the steps need not settle, and the two solutions' rounding drifts apart (6e-10 m at most
    in 20,000): there, to a micrometre."""
    rng = np.random.default_rng(seed)
    center, radius = rng.uniform(-8.0, 8.0, 2), 0.05
    near = math.atan2(-center[1], -center[0])
    angles = near + rng.uniform(-1.3, 1.3, n)
    xy = center + radius * np.column_stack([np.cos(angles), np.sin(angles)])
    xy += rng.normal(0.0, noise, (n, 2))
    fitted, residual = fit_circle_fixed_radius(xy, radius)
    centroid = xy.mean(axis=0)
    start = centroid * (1.0 + radius / np.linalg.norm(centroid))
    expected, expected_residual = _fit_circle_lstsq(xy, radius, start, 20)
    tolerance = 1e-12 if n >= 3 else 1e-6
    np.testing.assert_allclose(fitted, expected, rtol=0.0, atol=tolerance)
    assert residual == pytest.approx(expected_residual, abs=tolerance)


@pytest.mark.parametrize(
    "xy",
    [np.array([[1.0, 0.0]]), np.array([[1.0, 0.0], [1.0, 0.0]]),
     np.array([[1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])],  # one line through the start
)  # fmt: skip
def test_a_circle_fit_with_singular_steps_takes_the_minimum_norm_ones(xy: np.ndarray) -> None:
    fitted, residual = fit_circle_fixed_radius(xy, 0.05)
    centroid = xy.mean(axis=0)
    expected, expected_residual = _fit_circle_lstsq(
        xy, 0.05, centroid * (1.0 + 0.05 / np.linalg.norm(centroid)), 20
    )
    np.testing.assert_array_equal(fitted, expected)
    assert residual == expected_residual
    assert np.isfinite(fitted).all()


def test_no_flagged_returns_no_beacons() -> None:
    points = np.random.default_rng(0).normal(size=(100, 3))
    assert detect_beacons(points, np.zeros(100, bool), **DETECT) == ([], [])
    nan_points = np.full((5, 3), np.nan)
    assert detect_beacons(nan_points, np.ones(5, bool), **DETECT) == ([], [])


def cylinder_returns(count: int, noise_m: float, seed: int = 0) -> np.ndarray:
    """Flagged returns on the near side of a beacon 3 m ahead and 2 m left, at its height."""
    rng = np.random.default_rng(seed)
    centre, radius = np.array([3.0, 2.0]), BODY.beacon_radius_m
    near = math.atan2(-centre[1], -centre[0])
    angles = near + np.linspace(-1.0, 1.0, count)
    xy = centre + radius * np.column_stack([np.cos(angles), np.sin(angles)])
    xy += rng.normal(0.0, noise_m, xy.shape)
    z = np.full(count, DETECT["center_height_m"]) + rng.uniform(-0.2, 0.2, count)
    return np.column_stack([xy, z])


def test_a_loose_fit_below_the_quality_is_rejected() -> None:
    tight = cylinder_returns(20, 0.002)
    found, _ = detect_beacons(tight, np.ones(len(tight), bool), **DETECT, min_quality=0.6)
    assert len(found) == 1
    assert found[0].quality > 0.8
    assert found[0].bearing_rad == pytest.approx(math.atan2(2.0, 3.0), abs=math.radians(0.3))
    loose = cylinder_returns(11, 0.02, seed=3)
    found, rejected = detect_beacons(loose, np.ones(len(loose), bool), **DETECT)
    assert len(found) == 1  # no quality asked for
    quality = found[0].quality
    assert quality < 0.6
    found, rejected = detect_beacons(loose, np.ones(len(loose), bool), **DETECT, min_quality=0.6)
    assert found == []
    assert any(r.reason.startswith(f"fit quality {quality:.2f} below 0.6") for r in rejected)
