"""The event stream's odometry steps: the motion driven along the way, from the odometry log."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimation.app.config import Config
from estimation.app.events import EventMaker, _agreeing, _choose, _motion
from estimation.posegraph.events import Move, Start
from estimation.posegraph.graph import odometry_covariance
from estimation.posegraph.keys import pose_key
from sensors.geometry import se2
from sensors.scan3d.beacon import BeaconDetection
from sensors.trajio import pose_at

SPEED_M_S, TURN_RAD_S, RATE_HZ = 0.4, math.radians(45.0), 10.0


def drive(start: tuple[float, float, float], legs: list[tuple[str, float]],
          stand_s: float = 1.0) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """An odometry log at 10 Hz: standing ``stand_s``, then each leg ("go", metres ahead) or
    ("turn", radians in place), then standing again; yaw wrapped as a log holds it."""
    keys = [(0.0, *start)]
    t, (x, y, yaw) = stand_s, start
    keys.append((t, x, y, yaw))
    for kind, amount in legs:
        if kind == "go":
            t += abs(amount) / SPEED_M_S
            x, y = x + amount * math.cos(yaw), y + amount * math.sin(yaw)
        else:
            t += abs(amount) / TURN_RAD_S
            yaw += amount
        keys.append((t, x, y, yaw))
    keys.append((t + stand_s, x, y, yaw))
    k = np.array(keys)
    stamps = np.arange(0.0, k[-1, 0] + 1e-9, 1.0 / RATE_HZ)
    poses = np.column_stack([np.interp(stamps, k[:, 0], k[:, c]) for c in (1, 2, 3)])
    poses[:, 2] = np.angle(np.exp(1j * poses[:, 2]))
    return stamps, poses


def motion_of(stamps: np.ndarray, poses: np.ndarray, start_s: float,
              end_s: float) -> tuple[float, float]:  # fmt: skip
    before, after = pose_at(stamps, poses, start_s), pose_at(stamps, poses, end_s)
    return _motion(stamps, poses, start_s, end_s, before, after)


def test_motion_of_an_l_shaped_path_with_a_turn_in_place() -> None:
    # 2 m east, a quarter turn left in place, 1 m north: 5 s + 2 s + 2.5 s after 1 s standing.
    stamps, poses = drive((0.0, 0.0, 0.0), [("go", 2.0), ("turn", math.pi / 2), ("go", 1.0)])
    np.testing.assert_allclose(poses[-1], [2.0, 1.0, math.pi / 2], atol=1e-12)
    driven, turned = motion_of(stamps, poses, 1.0, 10.5)
    assert driven == pytest.approx(3.0, abs=1e-9)
    assert turned == pytest.approx(math.pi / 2, abs=1e-9)
    # The net move is shorter than the way driven.
    net = se2.between(poses[0], poses[-1])
    assert math.hypot(net[0], net[1]) == pytest.approx(math.sqrt(5.0))
    # Instants between samples, and standing time around the move, change nothing.
    assert motion_of(stamps, poses, 0.33, 11.27) == pytest.approx((3.0, math.pi / 2), abs=1e-9)
    # Part of the way: from 1 m along the first leg to halfway through the turn.
    assert motion_of(stamps, poses, 3.5, 7.0) == pytest.approx((1.0, math.pi / 4), abs=1e-9)


def test_motion_counts_every_turn_and_every_metre_however_the_net_move_ends() -> None:
    # Out and back (net zero), a turn and its undoing (net zero yaw).
    stamps, poses = drive((1.0, -2.0, 0.3), [("go", 1.5), ("turn", math.pi), ("go", 1.5),
                                             ("turn", -math.pi / 2), ("turn", math.pi / 2)])  # fmt: skip
    np.testing.assert_allclose(poses[-1][:2], poses[0][:2], atol=1e-9)
    driven, turned = motion_of(stamps, poses, stamps[0], stamps[-1])
    assert driven == pytest.approx(3.0, abs=1e-9)
    assert turned == pytest.approx(2 * math.pi, abs=1e-9)


def test_motion_turns_through_the_wrap_at_pi() -> None:
    # Heading 170°, a 20° left turn crosses ±180° in the log: 20° turned, not 340°.
    stamps, poses = drive((0.0, 0.0, math.radians(170.0)),
                          [("turn", math.radians(20.0)), ("go", 0.8)])  # fmt: skip
    assert poses[:, 2].min() < -3.0  # the log wraps
    assert poses[:, 2].max() > 3.0
    driven, turned = motion_of(stamps, poses, 0.0, stamps[-1])
    assert turned == pytest.approx(math.radians(20.0), abs=1e-9)
    assert driven == pytest.approx(0.8, abs=1e-9)


def test_standing_still_is_no_motion() -> None:
    stamps, poses = drive((0.0, 0.0, 3.1), [], stand_s=2.0)
    assert motion_of(stamps, poses, 0.5, 3.5) == (0.0, 0.0)


def test_a_move_entry_becomes_a_move_with_its_motion() -> None:
    config = Config()
    stamps, poses = drive((0.5, 0.5, 0.0), [("go", 2.0), ("turn", math.pi / 2), ("go", 1.0)])
    other = (stamps, np.tile([3.0, 3.0, 0.0], (len(stamps), 1)))
    starts = {"a": poses[0], "b": np.array([3.0, 3.0, 0.0])}
    maker = EventMaker(config, ["a", "b"], starts, {"a": (stamps, poses), "b": other})
    assert isinstance(maker.events[0], Start)
    entry = {"t_s": 10.5, "event": "move", "robot": "a", "from_index": 0, "to_index": 1,
             "start_s": 1.0}  # fmt: skip
    (move,) = maker.feed(1, entry, {})
    assert isinstance(move, Move)
    assert (move.robot, move.index) == ("a", 1)
    np.testing.assert_allclose(move.delta, [2.0, 1.0, math.pi / 2], atol=1e-9)
    assert move.motion == pytest.approx((3.0, math.pi / 2), abs=1e-9)
    factor = maker.builder.factors[-1]
    assert factor.keys == (pose_key("a", 0), pose_key("a", 1))
    g = maker.builder.settings
    expected = odometry_covariance(np.array(move.delta), g.odometry_sigma_m,
                                   g.odometry_sigma_per_m, g.odometry_sigma_rad,
                                   g.odometry_sigma_rad_per_rad, motion=(3.0, math.pi / 2))  # fmt: skip
    np.testing.assert_allclose(factor.covariance, expected, rtol=1e-9)
    # b has no pose in the graph yet: its move is held back, with its motion, until a fix.
    held = maker.feed(2, {**entry, "robot": "b"}, {})
    assert held == []
    assert maker.held_back == 1
    assert maker.pending["b"][0].motion == (0.0, 0.0)


def detection(range_m: float, bearing_deg: float, quality: float = 0.9) -> BeaconDetection:
    bearing = math.radians(bearing_deg)
    centre = np.array([range_m * math.cos(bearing), range_m * math.sin(bearing), 0.6])
    return BeaconDetection(range_m, bearing, centre, 20, 0.005, quality)


def test_the_detection_nearest_the_prediction_is_the_partner() -> None:
    near, far = detection(5.0, 93.0), detection(2.6, 106.6)
    assert _choose([far, near], (4.95, math.radians(92.7))) is near
    assert _choose([], (4.95, math.radians(92.7))) is None
    # Without an estimate: the only one, or the best fitted of several.
    assert _choose([far], None) is far
    assert _choose([detection(3.0, 10.0, 0.4), near], None) is near


def test_a_third_robots_beacon_is_not_taken_for_the_partners() -> None:
    """Robot c stands 2.6 m from a, 14° beside the line to b; b's beacon is not seen. Nearest
    the prediction of b is c's beacon, and the estimate places c there: it is not b's."""
    partner, third = (4.95, math.radians(92.7)), (2.62, math.radians(106.6))
    beacon_c = detection(2.6, 106.3)
    assert _choose([beacon_c], partner) is beacon_c  # what a two-robot chooser would take
    assert _choose([beacon_c], partner, [third]) is None
    beacon_b = detection(4.9, 93.1)
    assert _choose([beacon_c, beacon_b], partner, [third]) is beacon_b
    # A robot the estimate does not place yet rules nothing out.
    assert _choose([beacon_c], partner, [None]) is beacon_c


def test_a_first_observation_takes_the_detections_whose_ranges_agree() -> None:
    """No estimate of the partner yet: a sees b at 3.0 m and c at 2.2 m (c's beacon fits
    better); b sees a at 3.02 m and c at 1.4 m. Only a–b agree on the distance."""
    a_sees = [detection(2.2, 40.0, quality=0.95), detection(3.0, -10.0, quality=0.6)]
    b_sees = [detection(1.4, 80.0, quality=0.9), detection(3.02, 170.0, quality=0.5)]
    seen_a, seen_b = _agreeing(a_sees, b_sees)
    assert seen_a is a_sees[1]
    assert seen_b is b_sees[1]
    assert _agreeing([], b_sees) == (None, None)
    assert _agreeing(a_sees, []) == (None, None)
    # Equal agreement: the better fitted pair.
    twins = [detection(3.0, 0.0, quality=0.2), detection(3.0, 20.0, quality=0.8)]
    assert _agreeing(twins, [detection(3.0, 0.0)])[0] is twins[1]
