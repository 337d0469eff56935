"""The simulated mission built piece by piece: the timeline move by move, odometry drawn leg by
leg as the timeline grows, and the LMS telegrams recorded interval by interval."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sensors.geometry import se2
from sensors.lms200.capture import CaptureReader, CaptureWriter
from sensors.scan3d.mirror import MirrorGeometry
from sensors.sim.mission import (
    CollisionError,
    MissionError,
    Odometer,
    OdometryNoise,
    SensorRecorder,
    Timeline,
    TimelineBuilder,
    odometry,
)
from sensors.sim.planner import FreeSpace, free_space
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.sensing import RobotBody, SimulatedScanner
from sensors.sim.world import World, world_from_mapping
from tests.sensors.sim.conftest import box_room_document

BODY = RobotBody()
SPEED_M_S, TURN_RAD_S, DWELL_S = 0.4, math.radians(45.0), 2.0
STARTS = {"a": np.array([1.0, 1.0, 0.0]), "b": np.array([1.0, 3.0, math.radians(-90.0)])}
#: Noise large enough that a misplaced draw shows in every digit.
NOISE = OdometryNoise(sigma_m=0.01, sigma_per_m=0.05, sigma_rad=0.01, sigma_rad_per_rad=0.05)


def pillar_room(pillar_xy: tuple[float, float] = (3.0, 2.0)) -> World:
    """A 6 m × 4 m room with a 0.6 m pillar."""
    doc = box_room_document(footprint=[[0, 0], [6, 0], [6, 4], [0, 4]])
    doc["boxes"] = [{"name": "pillar", "center": list(pillar_xy), "size": [0.6, 0.6],
                     "z_m": [0.0, 2.5]}]  # fmt: skip
    return world_from_mapping(doc)


@pytest.fixture(scope="module")
def space() -> FreeSpace:
    return free_space(pillar_room(), robot_radius_m=0.3, robot_height_m=0.35, margin_m=0.0)


def builder_in(space: FreeSpace) -> TimelineBuilder:
    return TimelineBuilder(STARTS, space, SPEED_M_S, TURN_RAD_S, DWELL_S)


def state(timeline: Timeline, builder: TimelineBuilder) -> dict[str, Any]:
    """Everything a move may change, as plain values."""
    return copy.deepcopy(
        {
            "keys": {n: list(t.keys) for n, t in timeline.tracks.items()},
            "events": timeline.events,
            "stops": {n: [(t, p.tolist()) for t, p in s] for n, s in timeline.stops.items()},
            "legs": timeline.legs,
            "t": builder.t,
            "index": builder.index,
        }
    )


#: A mission flown step by step: (robot, target x, y, yaw_deg, path) or "dwell".
STEPS: list[Any] = [
    "dwell",
    ("a", 5.0, 1.0, 90.0, None),
    "dwell",
    ("b", 2.0, 3.2, 0.0, [(1.0, 3.0), (1.5, 3.4), (2.0, 3.2)]),
    "dwell",
    ("a", 4.5, 3.3, 170.0, None),  # around the pillar: the planner's legs
    "dwell",
    ("b", 0.8, 0.8, -135.0, None),
    "dwell",
]


def fly(builder: TimelineBuilder, step: Any) -> None:
    if step == "dwell":
        builder.dwell(phase="mapping")
        return
    robot, x, y, yaw_deg, path = step
    target = np.array([x, y, math.radians(yaw_deg)])
    waypoints = None if path is None else [np.array(p) for p in path]
    assert builder.move(robot, target, "test", waypoints)


def test_odometry_as_the_timeline_grows_equals_odometry_of_the_finished_timeline(
    space: FreeSpace,
) -> None:
    """The claim holds as stated: every robot draws from its own generator, so its draws come
    in its leg order whether the legs are drawn one at a time or all at once (the Odometer
    draws a leg's error the first time it evaluates a time after the leg was added)."""
    builder = builder_in(space)
    odometers = {r: Odometer(builder.timeline, r, NOISE, np.random.default_rng([9, k]))
                 for k, r in enumerate(STARTS)}  # fmt: skip
    grid = np.arange(0.0, 200.0, 0.1)
    pieces: dict[str, list[np.ndarray]] = {r: [] for r in STARTS}
    sent = 0
    for step in STEPS:
        fly(builder, step)
        new = grid[sent : int(np.searchsorted(grid, builder.t, side="right"))]
        sent += len(new)
        # The new instants, in two uneven pieces, each robot in turn.
        for part in np.array_split(new, [len(new) // 3]):
            for robot, odometer in odometers.items():
                pieces[robot].append(odometer.at(part))
    times = grid[:sent]
    assert times[-1] == pytest.approx(builder.t, abs=0.1)
    assert len(builder.timeline.legs["a"]) == len(builder.timeline.legs["b"]) == 2
    for k, robot in enumerate(STARTS):
        incremental = np.concatenate(pieces[robot])
        whole = odometry(builder.timeline, robot, times, NOISE, np.random.default_rng([9, k]))
        np.testing.assert_array_equal(incremental, whole)
        # Noisy, not the truth, but near it: the errors were drawn and applied.
        truth = builder.timeline.poses_at(robot, times)
        error = np.hypot(*(incremental[:, :2] - truth[:, :2]).T)
        assert 0.0 < error.max() < 1.0
        np.testing.assert_array_equal(incremental[0], STARTS[robot])


def test_each_legs_error_is_drawn_once(space: FreeSpace) -> None:
    builder = builder_in(space)
    rng = np.random.default_rng(4)
    odometer = Odometer(builder.timeline, "a", NOISE, rng)
    first = odometer.at(np.array([0.0, 0.5]))
    np.testing.assert_array_equal(first, [STARTS["a"], STARTS["a"]])
    fly(builder, STEPS[1])
    fly(builder, "dwell")
    times = np.linspace(0.0, builder.t, 57)
    once = odometer.at(times)
    again = odometer.at(times[::-1])[::-1]
    np.testing.assert_array_equal(once, again)
    expected = np.random.default_rng(4)
    expected.standard_normal(3)  # one leg so far: three draws
    assert rng.bit_generator.state == expected.bit_generator.state
    assert len(odometer.errors) == 1
    # Standing after the leg, the odometry holds the leg's end with its whole error.
    stop = se2.compose(STARTS["a"], se2.between(STARTS["a"], builder.timeline.tracks["a"].pose)
                       + odometer.errors[0])  # fmt: skip
    np.testing.assert_allclose(once[-1], stop, atol=1e-12)


def test_a_path_through_an_obstacle_is_refused_and_nothing_moves(space: FreeSpace) -> None:
    builder = builder_in(space)
    fly(builder, "dwell")
    before = state(builder.timeline, builder)
    # The second leg runs through the middle of the pillar: no local detour of 0.3 m gets past.
    through = [np.array([1.0, 1.0]), np.array([1.0, 2.0]), np.array([5.0, 2.0])]
    with pytest.raises(
        MissionError,
        match=r"^plan\[3\]: robot 'a' would collide on the leg \(1\.00, 2\.00\) → \(5\.00, 2\.00\)"
        r" of its path$",
    ):
        builder.move("a", np.array([5.0, 2.0, 0.0]), "plan[3]", through)
    assert state(builder.timeline, builder) == before
    across = [np.array([1.0, 3.0]), np.array([3.0, 3.1]), np.array([3.0, 0.9])]
    with pytest.raises(MissionError, match=r"robot 'b' .* leg \(3\.00, 3\.10\) → \(3\.00, 0\.90\)"):
        builder.move("b", np.array([3.0, 0.9, 0.0]), "goal", across)
    # A collision says where the robot's centre first came too close: just before the pillar
    # (x 2.7-3.3) by about the robot's radius (0.3 m, on a 0.1 m grid), on the leg.
    with pytest.raises(CollisionError) as caught:
        builder.move("a", np.array([5.0, 2.0, 0.0]), "plan[3]", through)
    assert caught.value.at_xy[1] == pytest.approx(2.0)
    assert 2.3 < caught.value.at_xy[0] < 2.6
    assert not space.is_free(caught.value.at_xy)
    assert space.first_blocked(np.array([1.0, 1.0]), np.array([1.0, 2.0])) is None
    with pytest.raises(MissionError, match=r"^goal: robot 'a' cannot stand at \(3, 2\): inside"):
        builder.move("a", np.array([3.0, 2.0, 0.0]), "goal")
    with pytest.raises(MissionError, match=r"cannot stand at \(7, 1\)"):
        builder.move("a", np.array([7.0, 1.0, 0.0]), "goal", [np.array([1.0, 1.0])])
    assert state(builder.timeline, builder) == before
    # The same goal along a clear path is flown, through its waypoint.
    clear = [np.array([1.0, 1.0]), np.array([3.0, 0.8]), np.array([5.0, 1.0])]
    assert builder.move("a", np.array([5.0, 1.0, 0.0]), "goal", clear)
    positions = [tuple(k[1:3]) for k in builder.timeline.tracks["a"].keys]
    assert (3.0, 0.8) in positions
    assert builder.timeline.events[-1] == {
        "t_s": round(builder.t, 6), "event": "move", "robot": "a", "from_index": 0,
        "to_index": 1, "start_s": round(before["t"], 6),
    }  # fmt: skip
    leg_m = math.dist((1.0, 1.0), (3.0, 0.8)) + math.dist((3.0, 0.8), (5.0, 1.0))
    turns_rad = 4 * abs(math.atan2(0.2, 2.0))  # onto each leg's heading, then onto yaw 0
    assert builder.t - before["t"] == pytest.approx(leg_m / SPEED_M_S + turns_rad / TURN_RAD_S)


def test_a_leg_grazing_an_obstacle_is_driven_around_it_within_the_local_deviation(
    space: FreeSpace,
) -> None:
    builder = builder_in(space)
    # y = 1.5 passes 0.2 m inside the pillar's clearance (y >= 1.4): a small detour.
    graze = [np.array([1.0, 1.0]), np.array([1.0, 1.5]), np.array([5.0, 1.5])]
    assert builder.move("a", np.array([5.0, 1.5, 0.0]), "goal", graze)
    keys = np.array(builder.timeline.tracks["a"].keys)
    samples = builder.timeline.poses_at("a", np.linspace(0.0, builder.t, 400))
    assert all(space.is_free(p[:2]) for p in samples)
    assert keys[:, 2].min() < 1.45  # it went round, below the leg
    assert np.abs(samples[samples[:, 0] > 1.01, 1] - 1.5).max() <= 0.3 + 1e-9
    np.testing.assert_allclose(keys[-1, 1:3], (5.0, 1.5))
    # A corner of the plan inside the pillar is cut: the robot drives on to the next one.
    cut = [np.array([5.0, 1.5]), np.array([3.0, 2.0]), np.array([5.0, 3.2])]
    assert builder.move("a", np.array([5.0, 3.2, 0.0]), "goal", cut)
    samples = builder.timeline.poses_at("a", np.linspace(builder.timeline.legs["a"][-1][0],
                                                         builder.t, 200))  # fmt: skip
    assert all(space.is_free(p[:2]) for p in samples)
    assert np.abs(samples[:, 0] - 5.0).max() < 1e-9  # straight up x = 5, not via (3, 2)


def test_a_target_already_reached_is_no_move(space: FreeSpace) -> None:
    builder = builder_in(space)
    before = state(builder.timeline, builder)
    assert not builder.move("b", STARTS["b"] + [0.0, 0.0, 2 * math.pi], "goal")
    assert not builder.move("b", STARTS["b"] + [5e-7, -5e-7, 5e-7], "goal")
    assert state(builder.timeline, builder) == before
    # A turn in place is a move.
    assert builder.move("b", STARTS["b"] + [0.0, 0.0, math.pi / 2], "goal")
    assert builder.t == pytest.approx((math.pi / 2) / TURN_RAD_S)
    assert builder.index["b"] == 1


def test_a_robot_must_start_where_it_fits(space: FreeSpace) -> None:
    with pytest.raises(MissionError, match=r"robot 'b' starts at \(3, 2\), where it does not fit"):
        TimelineBuilder({"a": STARTS["a"], "b": np.array([3.0, 2.0, 0.0])}, space, SPEED_M_S,
                        TURN_RAD_S, DWELL_S)  # fmt: skip


@pytest.fixture(scope="module")
def scenes() -> tuple[RaycastScene, RaycastScene]:
    """The room before and after the pillar moved."""
    return (
        RaycastScene(build_mesh(pillar_room())),
        RaycastScene(build_mesh(pillar_room((3.5, 2.5)))),
    )


def test_recording_interval_by_interval_gives_the_telegrams_of_one_recording(
    space: FreeSpace, scenes: tuple[RaycastScene, RaycastScene], tmp_path: Path
) -> None:
    """The noise-free scanner makes the draws irrelevant: the chunked recording consumes the
    generator in another order than one call over all instants, the bytes are the same."""
    builder = builder_in(space)
    for step in STEPS[:4]:
        fly(builder, step)
    builder.timeline.change_s = 9.0  # the pillar moves during a's first leg
    scanner = SimulatedScanner(
        MirrorGeometry(axis_offset_m=0.1, gear_ratio=80.0, nominal_motor_period_s=0.5),
        motor_period_s=0.503, arm_phase_time_s=0.1, edge_on_turn=7, range_sigma_m=0.0,
    )  # fmt: skip
    timeline = builder.timeline

    def scene_at(t: float) -> RaycastScene:
        return scenes[1] if t >= 9.0 else scenes[0]

    whole = SensorRecorder(None, "a", scanner, BODY, 0.45, 38400)
    instants = whole.due(builder.t)
    assert len(instants) > 150
    once = whole.record(timeline, scene_at, instants, np.random.default_rng(1))
    assert whole.telegrams == len(once) == len(instants)
    assert list(tmp_path.iterdir()) == []  # nothing written without a writer

    capture = tmp_path / "a.cap"
    with CaptureWriter(capture, {"robot": "a"}) as writer:
        pieces = SensorRecorder(writer, "a", scanner, BODY, 0.45, 38400)
        rng = np.random.default_rng(2)
        chunked: list[tuple[float, bytes]] = []
        for until in (0.05, 3.3, 8.95, 9.0, 9.07, 12.5, builder.t):
            due = pieces.due(until)
            for part in np.array_split(due, 3) if len(due) > 3 else [due]:
                chunked += pieces.record(timeline, scene_at, part, rng)
        assert len(pieces.due(builder.t)) == 0
    assert pieces.telegrams == len(once)
    assert [s for s, _ in chunked] == [s for s, _ in once]
    assert [d for _, d in chunked] == [d for _, d in once]
    reader = CaptureReader(capture)
    assert b"".join(d for _, d in reader.chunks()) == b"".join(d for _, d in once)
    assert [s for s, _ in reader.chunks()] == pytest.approx([s for s, _ in once], abs=1e-6)
    # The recording sees the robot move and the world change: the telegrams vary.
    assert len({d[10:-3] for _, d in once}) > 0.9 * len(once)


def test_recording_nothing_returns_nothing(space: FreeSpace) -> None:
    builder = builder_in(space)
    scanner = SimulatedScanner(
        MirrorGeometry(axis_offset_m=0.1, gear_ratio=80.0, nominal_motor_period_s=0.5),
        motor_period_s=0.5,
    )
    recorder = SensorRecorder(None, "a", scanner, BODY, 0.45, 38400)
    scene = RaycastScene(build_mesh(pillar_room()))
    assert recorder.record(builder.timeline, lambda _: scene, np.zeros(0),
                           np.random.default_rng(0)) == []  # fmt: skip
    assert recorder.telegrams == 0
