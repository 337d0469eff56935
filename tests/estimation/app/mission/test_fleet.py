"""The simulated fleet behind the Fleet interface: goals refused or driven by belief, and what
comes back from the robots (LMS bytes, odometry, event entries)."""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import pytest

from estimation.app.config import Config
from estimation.app.dataset import LmsDecoder
from estimation.app.mission.fleet import Goal, SimulatedFleet
from estimation.app.resources import resolve_builtin
from estimation.app.rig import scan_limits
from sensors.geometry import se2
from sensors.lms200.protocol.scan import scan_interval_s
from sensors.sim.planner import FreeSpace, free_space
from sensors.sim.world import World, load_world

CONFIG = Config()
STARTS = {"a": (2.0, 3.5, math.radians(20.0)), "b": (3.5, 5.75, math.radians(220.0))}


@pytest.fixture(scope="module")
def world() -> World:
    return load_world(resolve_builtin("worlds", "essex_lab"))


@pytest.fixture(scope="module")
def body_space(world: World) -> FreeSpace:
    """Where the body touches nothing (as ``simulated.fly`` builds it: no margin)."""
    robot = CONFIG.robot
    return free_space(world, robot_radius_m=robot.footprint_radius_m,
                      robot_height_m=robot.body_height_m, margin_m=0.0)  # fmt: skip


@pytest.fixture
def fleet(world: World, body_space: FreeSpace) -> SimulatedFleet:
    return SimulatedFleet(world, body_space, CONFIG, {r: np.array(p) for r, p in STARTS.items()},
                          seed=3)  # fmt: skip


def snapshot(fleet: SimulatedFleet) -> dict[str, Any]:
    timeline = fleet.timeline
    return copy.deepcopy({"keys": {r: list(t.keys) for r, t in timeline.tracks.items()},
                          "events": timeline.events, "legs": timeline.legs, "t": fleet.builder.t,
                          "index": fleet.builder.index})  # fmt: skip


def test_a_goal_whose_path_would_collide_is_refused(fleet: SimulatedFleet) -> None:
    before = snapshot(fleet)
    # Straight through pillar_1 (4.0, 4.5) to a free pose beyond it.
    status = fleet.move(Goal("a", (6.0, 5.5, 0.0), path=((2.0, 3.5), (6.0, 5.5))))
    assert (status.robot, status.ok, status.index) == ("a", False, 0)
    assert status.reason == (
        "goal of robot a: robot 'a' would collide on the leg (2.00, 3.50) → (6.00, 5.50) of its path"
    )
    assert fleet.refused == [status.reason]
    # The first leg is clear, the second runs through pillar_2 (8.2, 3.0): it is the one named.
    status = fleet.move(Goal("b", (10.0, 3.0, 0.0), path=((3.5, 5.75), (6.5, 3.0), (10.0, 3.0))))
    assert not status.ok
    assert status.reason == (
        "goal of robot b: robot 'b' would collide on the leg (6.50, 3.00) → (10.00, 3.00) of its path"
    )
    # A goal inside the pillar cannot be stood at, whatever the path.
    status = fleet.move(Goal("a", (4.0, 4.5, 0.0)))
    assert not status.ok
    assert status.reason is not None
    assert "cannot stand at (4, 4.5)" in status.reason
    assert len(fleet.refused) == 3
    assert snapshot(fleet) == before  # nothing moved, nothing logged
    got = fleet.receive()
    assert [e["event"] for e in got.events] == ["start", "start"]
    assert got.now_s == 0.0


def test_a_robot_driving_by_its_belief_ends_as_far_off_as_the_belief(
    fleet: SimulatedFleet, body_space: FreeSpace
) -> None:
    true_start = np.array(STARTS["a"])
    believed = true_start + np.array([0.25, -0.15, math.radians(8.0)])  # dx, dy, dyaw
    goal = (3.6, 2.6, math.radians(-30.0))
    path = ((float(believed[0]), float(believed[1])), (3.0, 2.4), (goal[0], goal[1]))
    status = fleet.move(Goal("a", goal, path=path, believed=tuple(believed.tolist())))
    assert status.ok, status.reason
    assert status.index == 1
    ended = fleet.timeline.tracks["a"].pose
    # Relative to where it truly started, it ended where the goal lies relative to the belief.
    np.testing.assert_allclose(se2.between(true_start, ended), se2.between(believed, goal),
                               atol=1e-9)  # fmt: skip
    assert math.dist(ended[:2], goal[:2]) > 0.2  # so not at the goal itself
    # It drove through the waypoint as the belief places it, seen from the truth.
    waypoint = se2.compose(true_start, se2.between(believed, np.array([3.0, 2.4, 0.0])))
    positions = np.array([k[1:3] for k in fleet.timeline.tracks["a"].keys])
    assert np.hypot(*(positions - waypoint[:2]).T).min() < 1e-9
    assert body_space.is_free(ended[:2])
    # Without a belief, the goal is absolute.
    status = fleet.move(Goal("b", (5.0, 6.5, math.radians(90.0))))
    assert status.ok, status.reason
    ended_b = fleet.timeline.tracks["b"].pose
    np.testing.assert_allclose(ended_b[:2], (5.0, 6.5), atol=1e-9)
    assert math.remainder(ended_b[2] - math.radians(90.0), 2 * math.pi) == pytest.approx(0.0)
    assert fleet.refused == []


def decode(fleet: SimulatedFleet, robot: str, decoder: LmsDecoder | None,
           chunks: list[tuple[float, bytes]]) -> LmsDecoder:  # fmt: skip
    if decoder is None:
        decoder = LmsDecoder(CONFIG.scanner.measuring_mode, scan_limits(CONFIG),
                             fleet.capture_header(robot))  # fmt: skip
    for stamp, data in chunks:
        decoder.feed(stamp, data)
    return decoder


def test_receive_returns_what_was_recorded_since_the_last_call(fleet: SimulatedFleet) -> None:
    assert fleet.move(Goal("a", (3.0, 2.0, 0.0))).ok
    fleet.dwell(phase="start", reference="a", mapper="b", step=-1)
    first = fleet.receive()
    now = fleet.builder.t
    assert first.now_s == now
    assert now > CONFIG.robot.speed_m_s  # it drove, then dwelt
    assert [e["event"] for e in first.events] == ["start", "start", "move", "dwell"]
    assert first.events[2]["robot"] == "a"
    assert first.events[3]["end_s"] == pytest.approx(now, abs=1e-6)
    interval = scan_interval_s(CONFIG.serial.baud_rate, 101, 1.0, True)
    decoders = {}
    for robot in STARTS:
        # Odometry at 10 Hz from 0 up to now.
        times, poses = first.odometry[robot]
        np.testing.assert_allclose(times, np.arange(len(times)) * 0.1, atol=1e-9)
        assert now - 0.1 < times[-1] <= now + 1e-9
        assert poses.shape == (len(times), 3)
        np.testing.assert_allclose(se2.between(poses[0], STARTS[robot]), 0.0, atol=1e-12)
        assert (np.abs(poses[:, 2]) <= math.pi).all()
        truth = fleet.timeline.poses_at(robot, times)
        assert np.hypot(*(poses[:, :2] - truth[:, :2]).T).max() < 0.1
        # LMS telegrams of continuous output, decodable as the loop decodes them.
        chunks = first.lms[robot]
        assert abs(len(chunks) - now / interval) <= 2
        assert all(np.diff([s for s, _ in chunks]) > 0)
        decoder = decode(fleet, robot, None, chunks)
        stream = decoder.stream()
        assert len(stream.scans) == len(chunks)
        assert (stream.checksum_failures, stream.bytes_skipped, stream.implausible) == (0, 0, {})
        decoders[robot] = decoder
    assert not np.array_equal(first.odometry["a"][1][-1], first.odometry["a"][1][0])  # a moved
    b_now = first.odometry["b"][1][-1]  # b did not
    np.testing.assert_allclose(se2.between(b_now, STARTS["b"]), 0.0, atol=1e-12)

    # Nothing new has happened: nothing new comes back.
    again = fleet.receive()
    assert again.events == []
    for robot in STARTS:
        assert len(again.odometry[robot][0]) == 0
        assert again.odometry[robot][1].shape == (0, 3)
        assert again.lms[robot] == []

    fleet.log("roles", reference="b", mapper="a", step=0)
    assert fleet.move(Goal("b", (5.0, 6.0, 0.0))).ok
    third = fleet.receive()
    assert [e["event"] for e in third.events] == ["roles", "move"]
    for robot in STARTS:
        times = np.concatenate([first.odometry[robot][0], third.odometry[robot][0]])
        np.testing.assert_allclose(times, np.arange(len(times)) * 0.1, atol=1e-9)
        assert third.odometry[robot][0][0] > first.odometry[robot][0][-1]
        assert fleet.builder.t - 0.1 < times[-1] <= fleet.builder.t + 1e-9
        # The stream continues across receives: the decoder takes the new bytes on.
        before = len(decoders[robot].scans)
        decode(fleet, robot, decoders[robot], third.lms[robot])
        stream = decoders[robot].stream()
        assert len(stream.scans) == before + len(third.lms[robot]) > before
        assert stream.implausible == {}
        steps = np.diff(stream.times_s) / interval
        np.testing.assert_allclose(steps, 1.0, atol=1e-6)  # no telegram lost or repeated


def test_a_refused_goal_says_where_the_way_was_blocked_in_the_robots_belief(
    fleet: SimulatedFleet, body_space: FreeSpace
) -> None:
    # Straight through pillar_1 (4.0, 4.5): blocked before it, on the leg.
    status = fleet.move(Goal("a", (6.0, 5.5, 0.0), path=((2.0, 3.5), (6.0, 5.5))))
    assert not status.ok
    assert status.blocked_xy is not None
    blocked = np.array(status.blocked_xy)
    assert not body_space.is_free(blocked)
    assert 0.35 < math.dist(blocked, (4.0, 4.5)) < 0.6  # its radius and the body's
    # Driving by a belief 0.25 m and 8° off, the point is where the belief places it.
    true_start = np.array(STARTS["a"])
    believed = true_start + np.array([0.25, -0.15, math.radians(8.0)])
    path = ((float(believed[0]), float(believed[1])), (6.0, 5.5))
    status = fleet.move(Goal("a", (6.0, 5.5, 0.0), path=path, believed=tuple(believed.tolist())))
    assert not status.ok
    assert status.blocked_xy is not None
    truly = se2.compose(true_start, se2.between(believed, np.r_[status.blocked_xy, 0.0]))
    assert not body_space.is_free(truly[:2])
    # Mapped back into the truth, it lies on the leg the robot truly drove.
    end = se2.compose(true_start, se2.between(believed, np.array([6.0, 5.5, 0.0])))[:2]
    along = np.clip((truly[:2] - true_start[:2]) @ (end - true_start[:2])
                    / np.sum((end - true_start[:2]) ** 2), 0.0, 1.0)  # fmt: skip
    nearest = true_start[:2] + along * (end - true_start[:2])
    assert math.dist(truly[:2], nearest) < 1e-9
    assert math.dist(status.blocked_xy, truly[:2]) > 0.1  # the belief's offset, not the truth
    # A goal that cannot be stood at names no point.
    assert fleet.move(Goal("a", (4.0, 4.5, 0.0))).blocked_xy is None
