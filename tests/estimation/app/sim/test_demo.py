"""The demo's simulated 360° view: geometry, noise model and outputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from estimation.app.config import Config, config_from_mapping
from estimation.app.resources import resolve_builtin
from estimation.app.sim.demo import DEFAULT_POSE, run_demo, simulate_view
from mapping.formats.ply import read_ply
from sensors.errors import WorldError
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.world import load_world


@pytest.fixture(scope="module")
def essex() -> tuple:
    world = load_world(resolve_builtin("worlds", "essex_lab"))
    return world, RaycastScene(build_mesh(world))


def test_view_without_noise_lands_on_the_world(essex: tuple) -> None:
    world, scene = essex
    exact = config_from_mapping({"simulation": {"range_sigma_m": 0.0}})
    view = simulate_view(world, DEFAULT_POSE, exact, np.random.default_rng(0), scene)
    # The scanner sits at the robot pose plus its mount offset (yaw 90°: x forward is map +y).
    np.testing.assert_allclose(view.T_map_scanner[:3, 3], [6.0, 4.6, 0.45], atol=1e-12)
    points = view.points_scanner @ view.T_map_scanner[:3, :3].T + view.T_map_scanner[:3, 3]
    assert points.min(axis=0) == pytest.approx([0.0, 0.0, 0.0], abs=2e-3)
    assert points.max(axis=0) == pytest.approx([12.0, 9.0, 3.0], abs=2e-3)
    # Rays through the windows find nothing; everything else returns (all within 8 m here).
    assert 0.9 < view.valid.mean() < 1.0
    # Below −5° every ray meets the floor within 5.1 m, before reaching the door (6.4 m away).
    steep = view.elevation_rad < np.radians(-5.0)
    assert view.valid[steep].all()
    door_ward = view.elevation_rad > np.radians(-3.0)
    assert not view.valid[door_ward].all()


def test_range_noise_matches_the_configuration(essex: tuple) -> None:
    world, scene = essex
    exact = config_from_mapping({"simulation": {"range_sigma_m": 0.0}})
    noisy_cfg = config_from_mapping({"simulation": {"range_sigma_m": 0.01}})
    clean = simulate_view(world, DEFAULT_POSE, exact, np.random.default_rng(0), scene)
    noisy = simulate_view(world, DEFAULT_POSE, noisy_cfg, np.random.default_rng(1), scene)
    both = clean.valid & noisy.valid
    error = noisy.range_m[both] - clean.range_m[both]
    assert np.std(error) == pytest.approx(0.01, rel=0.05)
    assert abs(np.mean(error)) < 1e-3
    # Ranges are quantised to the LMS unit (mm).
    np.testing.assert_allclose(
        noisy.range_m[both] * 1000, np.round(noisy.range_m[both] * 1000), atol=1e-6
    )


def test_max_range_invalidates_far_returns(essex: tuple) -> None:
    world, scene = essex
    short = config_from_mapping({"scanner": {"max_range_m": 3.0}})
    view = simulate_view(world, DEFAULT_POSE, short, np.random.default_rng(0), scene)
    assert view.range_m[view.valid].max() <= 3.0
    assert 0.2 < view.valid.mean() < 0.9


def test_run_demo_outputs(tmp_path: Path) -> None:
    result = run_demo(tmp_path, Config(), seed=3)
    assert {label for label, _ in result.outputs} >= {
        "point cloud (map frame, PLY)", "world top view + ceiling band",
    }  # fmt: skip
    cloud = read_ply(tmp_path / "view.ply")
    assert len(cloud["x"]) == result.points > 30_000
    assert result.rays == 360 * 106
    origin = np.array([6.0, 4.6, 0.45])
    distance = np.linalg.norm(
        np.column_stack([cloud["x"], cloud["y"], cloud["z"]]) - origin, axis=1
    )
    np.testing.assert_allclose(distance, cloud["range_m"], atol=1e-4)
    assert set(np.unique(cloud["surface_id"])) <= set(range(100))
    again = run_demo(tmp_path / "again", Config(), seed=3)
    assert again.points == result.points
    assert (tmp_path / "again" / "view.ply").read_bytes() == (tmp_path / "view.ply").read_bytes()
    assert "coopmap" in (tmp_path / "config.yaml").read_text(encoding="utf-8")


def test_demo_pose_outside_the_world_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(WorldError, match=r"demo pose \(20, 4\.5\) lies outside every room"):
        run_demo(tmp_path, Config(), pose=(20.0, 4.5, 0.0))
    assert not (tmp_path / "view.ply").exists()
