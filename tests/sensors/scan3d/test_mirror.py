"""The rotating-mirror scanner: eq. 4, motor and mirror estimation, and the whole simulated chain."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.app.resources import resolve_builtin
from sensors.errors import SensorError
from sensors.geometry.frames import scanner_pose_matrix
from sensors.lms200.protocol.scan import Scan, decode_scan
from sensors.lms200.protocol.stream import StreamParser, Telegram
from sensors.lms200.protocol.telegram import TURN_S
from sensors.scan3d.mirror import (
    MirrorGeometry,
    ScanClock,
    assemble_sweeps,
    elevation_at,
    estimate_mirror,
    fit_motor,
    mirror_points,
    scan_times,
)
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.sensing import SimulatedScanner, scan_stream, telegram_times
from sensors.sim.world import load_world

GEOMETRY = MirrorGeometry(axis_offset_m=0.1, gear_ratio=80.0, nominal_motor_period_s=0.5)


def reflect(range_m: float, bearing: float, psi: float, d: float) -> np.ndarray:
    """Ray-trace one beam off a plane mirror through the axis (x = d, z = 0) at angle ψ."""
    direction = np.array([math.cos(bearing), math.sin(bearing), 0.0])
    normal = np.array([-math.sin(psi), 0.0, math.cos(psi)])
    to_mirror = d / math.cos(bearing)
    hit = direction * to_mirror
    reflected = direction - 2 * (direction @ normal) * normal
    return hit + reflected * (range_m - to_mirror)


@settings(max_examples=200, deadline=None)
@given(st.floats(0.5, 8.0), st.floats(-0.87, 0.87), st.floats(-1.5, 1.5), st.floats(0.05, 0.3))
def test_eq4_is_the_reflection_geometry(
    range_m: float, bearing: float, psi: float, d: float
) -> None:
    expected = reflect(range_m, bearing, psi, d)
    got = mirror_points(np.array([range_m]), np.array([bearing]), np.array([2 * psi]), d)[0]
    np.testing.assert_allclose(got, expected, atol=1e-9)


def test_eq4_typo_is_corrected() -> None:
    # The paper prints z = (r cos θ − d) sin θ; the geometry gives sin φ. Here they differ.
    r, theta, phi, d = 4.0, math.radians(30), math.radians(60), 0.1
    point = mirror_points(np.array([r]), np.array([theta]), np.array([phi]), d)[0]
    assert point[2] == pytest.approx((r * math.cos(theta) - d) * math.sin(phi))
    assert point[2] != pytest.approx((r * math.cos(theta) - d) * math.sin(theta), abs=0.1)
    assert point[0] == pytest.approx(d + (r * math.cos(theta) - d) * math.cos(phi))
    assert point[1] == pytest.approx(r * math.sin(theta))


def test_motor_fit_is_robust_to_missed_and_spurious_edges() -> None:
    rng = np.random.default_rng(4)
    period = 0.5 * 1.012  # the motor runs 1.2 % slow
    turns = np.arange(80)
    turns = turns[rng.random(80) > 0.3]  # 30 % of the edges missed
    edges = 0.3 + turns * period + rng.uniform(-0.04, 0.04, len(turns))  # ±half a scan
    spurious = rng.uniform(edges[0], edges[-1], 6)
    fit = fit_motor(np.concatenate([edges, spurious]), nominal_period_s=0.5)
    assert fit.period_s == pytest.approx(period, rel=0.002)
    assert fit.edges_used >= len(edges) - 2
    assert fit.edges_rejected >= 4
    assert fit.residual_rms_s < 0.03


def test_motor_fit_needs_edges() -> None:
    with pytest.raises(SensorError, match="at least 3 arm edges"):
        fit_motor(np.array([0.0, 0.5]), 0.5)


def test_scan_times_unwrap_the_turn_counter() -> None:
    from sensors.lms200.protocol.scan import Scan
    from sensors.lms200.protocol.telegram import TURN_S

    turns = np.array([0, 6, 12, 300, 306, 1000])
    stamps = 5.0 + turns * TURN_S + np.array([0.01, 0.03, 0.0, 0.02, 0.05, 0.01])
    scans = [
        Scan(np.zeros(1), np.zeros(1), np.zeros(1, np.uint8), np.zeros(1, np.uint8), 0.001,
             scan_index=int(t % 256), stamp_s=float(s))
        for t, s in zip(turns, stamps, strict=True)
    ]  # fmt: skip
    times = scan_times(scans)
    np.testing.assert_allclose(np.diff(times), np.diff(turns) * TURN_S, atol=1e-12)
    assert (times <= stamps + 1e-12).all()
    assert np.min(stamps - times) == pytest.approx(0.0, abs=1e-12)


@pytest.fixture(scope="module")
def essex_scene() -> RaycastScene:
    return RaycastScene(build_mesh(load_world(resolve_builtin("worlds", "essex_lab"))))


def simulate(scene: RaycastScene, *, drop: float, seconds: float, seed: int = 0,
             pose: tuple[float, float, float] = (6.0, 4.5, 0.3)):  # type: ignore[no-untyped-def]  # fmt: skip
    scanner = SimulatedScanner(
        GEOMETRY, motor_period_s=0.5 * 1.008, arm_phase_time_s=0.137, edge_on_turn=21,
        arm_drop_fraction=drop, seed=seed,
    )  # fmt: skip
    times = telegram_times(0.0, seconds, 38400, 101, 1.0)
    truth = scanner.scan(
        scene, scanner_pose_matrix(*pose, 0.1, 0.45), times, np.random.default_rng(seed)
    )
    parser = StreamParser()
    decoded = [
        decode_scan(e, 1)
        for stamp, chunk in scan_stream(truth)
        for e in parser.feed(chunk, stamp)
        if isinstance(e, Telegram)
    ]
    return scanner, truth, decoded


def test_simulated_sweep_to_3d_points_matches_ray_cast_truth(essex_scene: RaycastScene) -> None:
    scanner, truth, decoded = simulate(essex_scene, drop=0.1, seconds=40.0)
    assert len(decoded) == len(truth.times_s) == 500
    times = scan_times(decoded)
    estimate = estimate_mirror(decoded, times, GEOMETRY)
    assert estimate.fine_phase
    assert estimate.motor_period_s == pytest.approx(scanner.motor_period_s, rel=0.005)
    sweeps = assemble_sweeps(decoded, times, estimate)
    assert len(sweeps) == 2  # 40 s: two half mirror turns
    for sweep in sweeps:
        rows = np.searchsorted(times, sweep.stamp_s)
        cols = np.round(np.degrees(sweep.bearing_rad) + 50).astype(int)
        expected = truth.truth_scanner[rows, cols]
        assert np.isfinite(expected).all()
        error = np.linalg.norm(sweep.points_scanner - expected, axis=1)
        assert np.median(error) < 0.02
        assert np.percentile(error, 95) < 0.03
        # Blind spots are gone: no arm samples, no edge-on elevations, nothing behind the mirror.
        assert np.degrees(sweep.bearing_rad).min() >= -50 + GEOMETRY.arm_samples - 1e-9
        assert np.abs(sweep.elevation_rad).min() >= 2 * GEOMETRY.edge_on_half_width_rad
        assert (np.abs(sweep.elevation_rad) <= math.pi / 2 + 1e-9).all()
        assert len(sweep) > 10_000
        assert sweep.end_s - sweep.start_s == pytest.approx(10.0, abs=0.3)
        trimmed = sweep.trimmed()  # points (in float32) and reflector marks only
        assert trimmed.points_scanner.dtype == np.float32
        # Rounded only: within float32's half ulp of every coordinate (< 1 µm within 8 m).
        np.testing.assert_allclose(trimmed.points_scanner, sweep.points_scanner,
                                   rtol=2.0**-24, atol=0.0)  # fmt: skip
        assert trimmed.reflector is sweep.reflector
        assert len(trimmed) == len(sweep)
        for name in ("range_m", "bearing_rad", "elevation_rad", "flags", "stamp_s"):
            assert getattr(trimmed, name).size == 0
            assert getattr(trimmed, name).dtype == getattr(sweep, name).dtype
        assert (trimmed.start_s, trimmed.end_s, trimmed.scans) == (
            sweep.start_s, sweep.end_s, sweep.scans
        )  # fmt: skip


def test_motor_rate_within_half_a_percent_with_a_tenth_of_the_edges_dropped(
    essex_scene: RaycastScene,
) -> None:
    for seed in range(3):
        scanner, _, decoded = simulate(essex_scene, drop=0.1, seconds=20.0, seed=seed)
        estimate = estimate_mirror(decoded, scan_times(decoded), GEOMETRY)
        assert estimate.motor_rate_hz == pytest.approx(1 / scanner.motor_period_s, rel=0.005)


def test_elevation_follows_the_true_mirror(essex_scene: RaycastScene) -> None:
    _scanner, truth, decoded = simulate(essex_scene, drop=0.0, seconds=20.0)
    times = scan_times(decoded)
    estimate = estimate_mirror(decoded, times, GEOMETRY)
    phi = elevation_at(times, estimate)
    valid = np.abs(truth.elevation_rad) < math.radians(85)
    error = np.angle(np.exp(1j * (phi - truth.elevation_rad)))[valid]
    assert np.degrees(np.abs(error)).max() < 0.3


def test_no_edge_on_signature_is_an_error(essex_scene: RaycastScene) -> None:
    _, _, decoded = simulate(essex_scene, drop=0.0, seconds=4.0)  # a quarter of a sweep
    times = scan_times(decoded)
    with pytest.raises(SensorError, match="no edge-on signature"):
        estimate_mirror(decoded[:30], times[:30], GEOMETRY)


def counter_scans(turns: np.ndarray, stamps: np.ndarray, indexed: bool = True) -> list[Scan]:
    """One-sample scans at mirror turns ``turns`` (counter mod 256), received at ``stamps``."""
    return [
        Scan(np.zeros(1), np.zeros(1), np.zeros(1, np.uint8), np.zeros(1, np.uint8), 0.001,
             scan_index=int(t % 256) if indexed else None, stamp_s=float(s))
        for t, s in zip(turns, stamps, strict=True)
    ]  # fmt: skip


def test_scan_clock_fed_scan_by_scan_gives_scan_times_of_the_scans_so_far() -> None:
    rng = np.random.default_rng(3)
    # Steps of 6 turns, gaps of one to a few telegrams, and gaps past the 256-turn wrap.
    steps = rng.choice([6, 6, 6, 12, 18], 300)
    steps[[40, 41, 120, 200]] = [250, 262, 600, 1030]
    turns = 17 + np.concatenate([[0], np.cumsum(steps)])
    # Receive latency varies: the anchor (running minimum) moves several times.
    latency = rng.uniform(0.0, 0.06, len(turns))
    stamps = 3.0 + turns * TURN_S + latency
    scans = counter_scans(turns, stamps)
    clock = ScanClock()
    for n, scan in enumerate(scans, 1):
        clock.add(scan)
        if n in (1, 2, 41, 42, 43, 150, len(scans)) or n % 37 == 0:
            np.testing.assert_array_equal(clock.times(), scan_times(scans[:n]))
            # Independently: the true turns since the first scan, anchored at or before the
            # earliest-arriving stamp so far.
            relative = (turns[:n] - turns[0]) * TURN_S
            np.testing.assert_array_equal(clock.times(), relative + np.min(stamps[:n] - relative))
    times = clock.times()
    assert len(times) == len(scans)
    np.testing.assert_allclose(np.diff(times), np.diff(turns) * TURN_S, atol=1e-9)
    assert (times <= stamps + 1e-12).all()
    assert np.min(stamps - times) == pytest.approx(0.0, abs=1e-12)


def test_scan_clock_extended_in_chunks_counts_the_same_turns() -> None:
    """A capture's scans are added in chunks of any size (a whole capture at once, or as
    received): the turns, wraps included, and the anchor are those of the scans' true turns."""
    rng = np.random.default_rng(5)
    steps = rng.choice([6, 6, 12], 400)
    steps[[10, 11, 250, 399]] = [256, 262, 1030, 512]
    turns = 3 + np.concatenate([[0], np.cumsum(steps)])
    stamps = 7.0 + turns * TURN_S + rng.uniform(0.0, 0.05, len(turns))
    scans = counter_scans(turns, stamps)
    relative = (turns - turns[0]) * TURN_S
    expected = relative + np.min(stamps - relative)
    for sizes in ([len(scans)], [1, 10, 1, 200], [7] * 60):
        clock, start = ScanClock(), 0
        for size in [*sizes, len(scans)]:
            clock.extend(scans[start : start + size])
            start = min(len(scans), start + size)
        np.testing.assert_allclose(clock.times(), expected, rtol=0, atol=1e-9)
        assert clock.turns == (turns - turns[0]).tolist()
    # A scan without an index inside a chunk: the stream falls back to the stamps.
    mixed = list(scans)
    mixed[30] = counter_scans(turns[30:31], stamps[30:31], indexed=False)[0]
    clock = ScanClock()
    clock.extend(mixed[:20])
    clock.extend(mixed[20:])
    np.testing.assert_array_equal(clock.times(), stamps)
    # A scan without a stamp inside a chunk: the ones before it are added, then the error.
    clock = ScanClock()
    with pytest.raises(SensorError, match="every scan needs a host stamp"):
        clock.extend([*scans[:5], replace(scans[5], stamp_s=None), *scans[6:]])
    first = relative[:5] + np.min(stamps[:5] - relative[:5])
    np.testing.assert_allclose(clock.times(), first, rtol=0, atol=1e-9)
    assert clock.turns == (turns[:5] - turns[0]).tolist()
    for bad in (math.nan, math.inf):
        with pytest.raises(SensorError, match="not a finite time"):
            clock.extend([replace(scans[5], stamp_s=bad)])
    assert clock.turns == (turns[:5] - turns[0]).tolist()  # nothing added


def test_scan_clock_without_indices_gives_the_stamps() -> None:
    turns = np.arange(0, 60, 6)
    stamps = 1.0 + turns * TURN_S + np.linspace(0.0, 0.02, len(turns))
    clock = ScanClock()
    for scan in counter_scans(turns, stamps, indexed=False):
        clock.add(scan)
    np.testing.assert_array_equal(clock.times(), stamps)
    np.testing.assert_array_equal(scan_times(counter_scans(turns, stamps, indexed=False)), stamps)
    # One scan without an index among indexed ones: the stream falls back to the stamps.
    mixed = counter_scans(turns, stamps)
    mixed[4] = counter_scans(turns[4:5], stamps[4:5], indexed=False)[0]
    clock = ScanClock()
    for scan in mixed:
        clock.add(scan)
    np.testing.assert_array_equal(clock.times(), stamps)
    np.testing.assert_array_equal(scan_times(mixed), stamps)
    assert ScanClock().times().shape == (0,)


def test_a_scan_without_a_stamp_cannot_be_placed_in_time() -> None:
    scans = counter_scans(np.array([0, 6]), np.array([1.0, 1.08]))
    unstamped = replace(scans[1], stamp_s=None)
    clock = ScanClock()
    clock.add(scans[0])
    with pytest.raises(SensorError, match="every scan needs a host stamp"):
        clock.add(unstamped)
    np.testing.assert_array_equal(clock.times(), scan_times(scans[:1]))  # nothing was added
    with pytest.raises(SensorError, match="every scan needs a host stamp"):
        scan_times([scans[0], unstamped])


def test_arm_and_edge_on_tests_over_a_sweep_match_scan_by_scan_with_mixed_variants() -> None:
    """Scans of two variants (181 and 361 samples) in one stretch: the stacked tests give each
    scan the answer of its own samples."""
    from sensors.lms200.protocol.scan import scan_bearings
    from sensors.scan3d.mirror import arm_blocked, edge_on_times

    rng = np.random.default_rng(5)
    geometry = GEOMETRY
    scans = []
    for k in range(300):
        count = 181 if k % 3 else 361
        ranges = rng.uniform(0.02, 6.0, count)
        if rng.random() < 0.3:
            ranges[:40] = 0.05  # the arm over the right-most samples
        bearings = scan_bearings(count, False, 0.0)
        if 100 <= k < 110:  # the mirror edge-on: the central beams short
            ranges[np.abs(bearings) < geometry.edge_on_beams_rad * 0.8] = 0.01
        ranges[rng.random(count) < 0.05] = np.nan
        scans.append(Scan(ranges, bearings, np.zeros(count, np.uint8),
                          np.zeros(count, np.uint8), 0.001))  # fmt: skip
    blocked = arm_blocked(scans, 40, 0.25)
    expected = [np.count_nonzero(s.ranges_m[:40] < 0.25) * 2 > 40 for s in scans]
    assert blocked.tolist() == expected
    assert 50 < blocked.sum() < 150
    times = np.arange(300) * 0.0133
    centres = edge_on_times(scans, times, geometry)
    assert centres == pytest.approx([0.25 * (times[99] + times[100] + times[109] + times[110])])


def test_a_sweeps_samples_are_the_same_stacked_or_scan_by_scan() -> None:
    """The stacked path (scans of one variant and mode) keeps the samples the scan-by-scan one
    keeps, in the same order; a stretch that mixes variants takes the scan-by-scan path."""
    from sensors.lms200.protocol.scan import SpecialCode, scan_bearings
    from sensors.scan3d.mirror import _samples

    rng = np.random.default_rng(9)
    bearings = scan_bearings(181, False, 0.0)
    scans = []
    for _ in range(40):
        code = np.where(rng.random(181) < 0.1, SpecialCode.DAZZLE, SpecialCode.VALID)
        scans.append(Scan(rng.uniform(0.02, 8.0, 181), bearings, rng.integers(0, 4, 181, np.uint8),
                          code.astype(np.uint8), 0.001, measuring_mode=1))  # fmt: skip
    phi, times = rng.uniform(-1.0, 1.0, 40), np.arange(40) * 0.0133
    stacked = _samples(scans, phi, times, GEOMETRY)
    odd = Scan(np.full(361, 3.0), scan_bearings(361, False, 0.0), np.zeros(361, np.uint8),
               np.zeros(361, np.uint8), 0.001, measuring_mode=1)  # fmt: skip
    mixed = _samples([*scans, odd], np.r_[phi, 0.0], np.r_[times, 1.0], GEOMETRY)
    n = len(stacked[0])
    assert 40 * 181 * 0.5 < n < 40 * 181
    for a, b in zip(stacked, mixed, strict=True):
        np.testing.assert_array_equal(a, b[:n])
    assert stacked[4].any()  # reflector bits in mode 1
    assert not stacked[4].all()
    beyond = 3.0 * np.cos(odd.bearing_rad[GEOMETRY.arm_samples :]) > GEOMETRY.axis_offset_m + 0.02
    assert len(mixed[0]) == n + np.count_nonzero(beyond)
