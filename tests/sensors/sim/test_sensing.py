"""Simulated sensing of other robots, and where robots can drive."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from sensors.errors import SensorError
from sensors.geometry.frames import scanner_pose_matrix
from sensors.scan3d.mirror import MirrorGeometry
from sensors.sim.planner import free_space
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.sensing import (
    RobotBody,
    SimulatedScanner,
    robot_cylinders,
    world_with_robots,
)
from sensors.sim.world import World, load_world, world_from_mapping
from tests.sensors.sim.conftest import box_room_document

BODY = RobotBody()
SCANNER = SimulatedScanner(
    MirrorGeometry(axis_offset_m=0.1, gear_ratio=80.0, nominal_motor_period_s=0.5),
    motor_period_s=0.5, edge_on_turn=5, range_sigma_m=0.0,
)  # fmt: skip


def big_room() -> World:
    doc = box_room_document()
    doc["rooms"][0]["footprint"] = [[0, 0], [12, 0], [12, 8], [0, 8]]
    doc["rooms"][0]["ceiling_m"] = 3.0
    return world_from_mapping(doc)


def test_analytic_robots_match_meshed_robots() -> None:
    world = big_room()
    other = (7.0, 4.5, 2.0)
    meshed = world_with_robots(world, {"b": other}, BODY)
    mesh_scene = RaycastScene(build_mesh(meshed, cylinder_segments=512))
    plain_scene = RaycastScene(build_mesh(world))
    times = np.arange(0.0, 20.0, 0.08)
    T = scanner_pose_matrix(2.0, 4.0, 0.1, 0.1, 0.45)
    cylinders = np.broadcast_to(robot_cylinders(BODY, np.array([other])), (len(times), 2, 6))
    a = SCANNER.scan(mesh_scene, T, times, np.random.default_rng(0))
    b = SCANNER.scan(plain_scene, T, times, np.random.default_rng(0), cylinders=cylinders)
    both = np.isfinite(a.ranges_m) & np.isfinite(b.ranges_m)
    assert np.isfinite(a.ranges_m).sum() == np.isfinite(b.ranges_m).sum()
    np.testing.assert_allclose(a.ranges_m[both], b.ranges_m[both], atol=2e-3)
    np.testing.assert_array_equal(a.flags, b.flags)
    assert (b.flags > 0).sum() >= 5  # the beacon, 5 m away, was seen and flagged


def test_moving_scanner_takes_one_pose_per_scan() -> None:
    scene = RaycastScene(build_mesh(big_room()))
    times = np.arange(0.0, 2.0, 0.08)
    poses = np.stack([scanner_pose_matrix(2.0 + 0.2 * t, 4.0, 0.0, 0.1, 0.45) for t in times])
    moving = SCANNER.scan(scene, poses, times, np.random.default_rng(0))
    still = SCANNER.scan(scene, poses[0], times, np.random.default_rng(0))
    # Driving towards the far wall shortens the forward ranges over time.
    forward = np.abs(moving.bearing_rad) < math.radians(5)
    valid = np.isfinite(moving.ranges_m[:, forward]).all(axis=1) & np.isfinite(
        still.ranges_m[:, forward]
    ).all(axis=1)
    assert valid.sum() > 3
    assert (
        moving.ranges_m[valid][:, forward].mean(axis=1)
        < still.ranges_m[valid][:, forward].mean(axis=1) + 1e-9
    ).all()
    with pytest.raises(SensorError, match="one scanner pose or one per scan"):
        SCANNER.scan(scene, poses[:3], times, np.random.default_rng(0))


def test_free_space_respects_walls_doors_and_obstacles() -> None:
    world = load_world("configs/worlds/office_loop.yaml")
    space = free_space(world, robot_radius_m=0.3, robot_height_m=0.35)
    assert space.is_free((1.0, 1.0))
    assert not space.is_free((15.0, 10.0))  # the core between the office rows
    assert not space.is_free((0.1, 1.0))  # too close to a wall
    assert not space.is_free((-3.0, 1.0))  # outside every room
    legs = space.path(np.array([1.0, 1.0]), np.array([4.0, 4.0]))  # into an office by its door
    assert legs is not None
    assert all(space.segment_free(a, b) for a, b in itertools.pairwise(legs))
    assert any(abs(p[0] - 4.0) < 0.35 and abs(p[1] - 2.5) < 0.5 for p in legs)  # through the door
    assert space.path(np.array([1.0, 1.0]), np.array([15.0, 10.0])) is None
    assert space.component_of((1.0, 1.0)).sum() > 0.3 * space.free.sum()


def test_free_space_needs_sane_parameters() -> None:
    with pytest.raises(SensorError, match="positive resolution"):
        free_space(big_room(), robot_radius_m=0.0, robot_height_m=0.3)


def test_the_telegram_counter_runs_on_across_chunks_of_a_mission(tmp_path: Path) -> None:
    """A simulated capture's telegram index counts on mod 256, as the sensor's does."""
    from estimation.app.sim.simulate import run_simulation
    from sensors.lms200.capture import CaptureReader
    from sensors.lms200.protocol.scan import decode_scan
    from sensors.lms200.protocol.stream import StreamParser, Telegram
    from tests.paths import REPO

    out = tmp_path / "essex"
    run_simulation(REPO / "configs" / "missions" / "essex_lab.yaml", out)
    parser = StreamParser()
    indices = [
        decode_scan(event).telegram_index
        for _, chunk in CaptureReader(out / "robots" / "a" / "lms.cap").chunks()
        for event in parser.feed(chunk)
        if isinstance(event, Telegram)
    ]
    assert len(indices) > 3000  # more than one 1,500-scan chunk
    assert set(np.diff(np.array(indices, dtype=int)) % 256) == {1}
