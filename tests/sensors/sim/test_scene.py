"""Meshing a world and ray casting against it, checked against analytic geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensors.errors import SensorError
from sensors.sim.scene import RaycastScene, build_mesh, view_directions
from sensors.sim.world import World, world_from_mapping
from tests.sensors.sim.conftest import box_room_document

# Open3D casts in float32: ranges of a few metres are good to a few micrometres.
RANGE_TOL_M = 2e-5
ROOM = np.array([4.0, 3.0, 2.5])


def analytic_box_room(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Distance to the first wall/floor/ceiling of the 4 × 3 × 2.5 m room, and its name."""
    with np.errstate(divide="ignore", invalid="ignore"):
        upper = (ROOM - origins) / directions
        lower = -origins / directions
    t = np.where(directions > 0, upper, np.where(directions < 0, lower, np.inf))
    axis = np.argmin(t, axis=1)
    positive = directions[np.arange(len(axis)), axis] > 0
    names = {
        (0, True): "r/wall_1", (0, False): "r/wall_3", (1, True): "r/wall_2",
        (1, False): "r/wall_0", (2, True): "r/ceiling", (2, False): "r/floor",
    }  # fmt: skip
    return t.min(axis=1), [names[(int(a), bool(p))] for a, p in zip(axis, positive, strict=True)]


def test_box_room_ranges_and_surfaces_are_exact(box_room: World) -> None:
    mesh = build_mesh(box_room)
    scene = RaycastScene(mesh)
    rng = np.random.default_rng(7)
    origins = rng.uniform([0.2, 0.2, 0.2], ROOM - 0.2, size=(2000, 3))
    directions = rng.normal(size=(2000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    hits = scene.cast(origins, directions)
    expected, names = analytic_box_room(origins, directions)
    np.testing.assert_allclose(hits.range_m, expected, atol=RANGE_TOL_M)
    got = [mesh.surfaces[i].name for i in hits.surface_id]
    # Rays that end within a hair of an edge may be credited to either surface.
    clear = np.abs(np.sort(analytic_gaps(origins, directions), axis=1)[:, 1]) > 1e-4
    assert [g for g, c in zip(got, clear, strict=True) if c] == [
        n for n, c in zip(names, clear, strict=True) if c
    ]
    assert clear.mean() > 0.99


def analytic_gaps(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Per ray, distance of the first plane hit minus the others (for edge-tie detection)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(
            directions > 0,
            (ROOM - origins) / directions,
            np.where(directions < 0, -origins / directions, np.inf),
        )
    return t - t.min(axis=1, keepdims=True)


def test_axis_rays_hit_the_expected_surfaces(box_room: World) -> None:
    mesh = build_mesh(box_room)
    origin = np.array([1.0, 1.5, 1.2])
    directions = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    hits = RaycastScene(mesh).cast(origin, directions)
    np.testing.assert_allclose(hits.range_m, [3.0, 1.0, 1.5, 1.5, 1.3, 1.2], atol=RANGE_TOL_M)
    assert [mesh.surfaces[i].name for i in hits.surface_id] == [
        "r/wall_1", "r/wall_3", "r/wall_2", "r/wall_0", "r/ceiling", "r/floor",
    ]  # fmt: skip
    # Room surfaces face into the room.
    np.testing.assert_allclose(np.abs(hits.normal), np.abs(directions), atol=1e-6)
    np.testing.assert_allclose(hits.normal, -directions, atol=1e-6)


def test_rays_leave_through_openings_only() -> None:
    door = {"wall": 0, "from_m": 1.0, "to_m": 2.0, "bottom_m": 0.0, "top_m": 2.0}
    window = {"wall": 1, "from_m": 1.0, "to_m": 2.0, "bottom_m": 1.0, "top_m": 2.0}
    world = world_from_mapping(box_room_document(openings=[door, window]))
    mesh = build_mesh(world)
    origins = np.array([[1.5, 1.5, 1.0], [1.5, 1.5, 2.2], [3.0, 1.5, 1.5], [3.0, 1.5, 0.5]])
    directions = np.array([[0, -1, 0], [0, -1, 0], [1, 0, 0], [1, 0, 0]])
    hits = RaycastScene(mesh).cast(origins, directions)
    assert not hits.hit[0]
    assert hits.surface_id[0] == -1
    assert hits.range_m[1] == pytest.approx(1.5, abs=RANGE_TOL_M)  # wall above the door
    assert mesh.surfaces[hits.surface_id[1]].name == "r/wall_0"
    assert not hits.hit[2]  # through the window
    assert hits.range_m[3] == pytest.approx(1.0, abs=RANGE_TOL_M)  # wall below the window
    assert np.isnan(hits.normal[0]).all()


def test_boxes_and_cylinders_ranges_flags() -> None:
    doc = box_room_document()
    doc["boxes"] = [
        {
            "name": "crate",
            "center": [2.0, 1.5],
            "size": [0.4, 0.4],
            "z_m": [0.0, 1.0],
            "movable": True,
        },
        {
            "name": "diamond",
            "center": [2.0, 0.6],
            "size": [0.5, 0.5],
            "z_m": [0.0, 1.0],
            "yaw_deg": 45.0,
        },
    ]
    doc["cylinders"] = [
        {
            "name": "post",
            "center": [3.0, 2.4],
            "radius_m": 0.2,
            "z_m": [0.0, 2.0],
            "retroreflective": True,
        }
    ]
    world = world_from_mapping(doc)
    segments = 256
    mesh = build_mesh(world, cylinder_segments=segments)
    scene = RaycastScene(mesh)
    origins = np.array([[0.5, 1.5, 0.5], [0.5, 0.6, 0.5], [1.0, 2.4, 1.0], [2.0, 1.5, 2.0]])
    directions = np.array([[1, 0, 0], [1, 0, 0], [1, 0, 0], [0, 0, -1]])
    hits = scene.cast(origins, directions)
    half_diagonal = 0.25 * math.sqrt(2.0)
    assert hits.range_m[0] == pytest.approx(1.3, abs=RANGE_TOL_M)
    assert hits.range_m[1] == pytest.approx(1.5 - half_diagonal, abs=RANGE_TOL_M)  # the corner
    facet = 0.2 * (1 - math.cos(math.pi / segments))
    assert 1.8 - RANGE_TOL_M <= hits.range_m[2] <= 1.8 + facet + RANGE_TOL_M
    assert hits.range_m[3] == pytest.approx(1.0, abs=RANGE_TOL_M)  # top of the crate
    names = [mesh.surfaces[i].name for i in hits.surface_id]
    assert names == ["crate", "diamond", "post", "crate"]
    np.testing.assert_allclose(hits.normal[0], [-1, 0, 0], atol=1e-6)  # solids face outwards
    movable, reflective = mesh.surface_flags("movable"), mesh.surface_flags("retroreflective")
    assert movable[hits.surface_id].tolist() == [True, False, False, True]
    assert reflective[hits.surface_id].tolist() == [False, False, True, False]
    assert mesh.surface_id("post") == hits.surface_id[2]
    with pytest.raises(KeyError, match="no surface called 'nothing'"):
        mesh.surface_id("nothing")


def test_mesh_area_matches_the_world(box_room: World) -> None:
    mesh = build_mesh(box_room)
    walls = 2 * (4.0 + 3.0) * 2.5
    assert mesh.triangle_areas().sum() == pytest.approx(walls + 2 * 12.0, rel=1e-12)
    no_ceiling = build_mesh(box_room, ceilings=False)
    assert no_ceiling.triangle_areas().sum() == pytest.approx(walls + 12.0, rel=1e-12)
    door = {"wall": 0, "from_m": 1.0, "to_m": 2.0, "bottom_m": 0.0, "top_m": 2.0}
    with_door = build_mesh(world_from_mapping(box_room_document(openings=[door])))
    assert with_door.triangle_areas().sum() == pytest.approx(walls + 24.0 - 2.0, rel=1e-12)


def test_overlapping_openings_remove_their_union() -> None:
    a = {"wall": 0, "from_m": 1.0, "to_m": 2.0, "bottom_m": 0.0, "top_m": 2.0}
    b = {"wall": 0, "from_m": 1.5, "to_m": 3.0, "bottom_m": 1.0, "top_m": 2.0}
    mesh = build_mesh(world_from_mapping(box_room_document(openings=[a, b])))
    full = 2 * (4.0 + 3.0) * 2.5 + 24.0
    assert mesh.triangle_areas().sum() == pytest.approx(full - (2.0 + 1.0), rel=1e-12)


@pytest.mark.parametrize(
    ("origins", "directions", "message"),
    [
        (np.zeros((2, 3)), np.zeros((2, 3)), "non-zero"),
        (np.full((1, 3), np.nan), np.ones((1, 3)), "finite"),
        (np.zeros((1, 2)), np.ones((1, 2)), r"\(N, 3\)"),
    ],
)
def test_bad_rays_are_rejected(
    box_room: World, origins: np.ndarray, directions: np.ndarray, message: str
) -> None:
    with pytest.raises(SensorError, match=message):
        RaycastScene(build_mesh(box_room)).cast(origins, directions)


def test_height_map_sees_the_tops_of_objects() -> None:
    doc = box_room_document()
    doc["boxes"] = [{"name": "crate", "center": [1.0, 1.0], "size": [0.6, 0.6], "z_m": [0, 0.8]}]
    scene = RaycastScene(build_mesh(world_from_mapping(doc), ceilings=False))
    heights, surfaces = scene.height_map(np.array([-1.0, -1.0]), np.array([5.0, 4.0]), 0.1, 5.0)
    assert heights.shape == (50, 60)
    row, col = int((1.0 + 1.0) / 0.1), int((1.0 + 1.0) / 0.1)  # cell around (1.05, 1.05)
    assert heights[row, col] == pytest.approx(0.8, abs=1e-5)
    assert heights[row + 10, col + 10] == pytest.approx(0.0, abs=1e-5)  # floor at (2.05, 2.05)
    assert np.isnan(heights[0, 0])
    assert surfaces[0, 0] == -1
    inside = ~np.isnan(heights)
    assert inside.sum() == pytest.approx(40 * 30, abs=2 * (40 + 30))


def test_view_directions_lattice() -> None:
    directions, azimuth, elevation = view_directions(
        math.radians(1.0), math.radians(-45.0), math.radians(60.0), math.radians(1.0)
    )
    assert len(azimuth) == 360
    assert len(elevation) == 106
    assert directions.shape == (360 * 106, 3)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-12)
    grid = directions.reshape(106, 360, 3)
    np.testing.assert_allclose(np.degrees(np.arcsin(grid[:, 0, 2])), np.linspace(-45, 60, 106))
    with pytest.raises(SensorError, match="positive"):
        view_directions(0.0, -1.0, 1.0, 0.1)


def test_open3d_mesh_matches_and_is_closed(box_room: World) -> None:
    mesh = build_mesh(box_room)
    legacy = mesh.to_open3d()
    assert len(legacy.triangles) == len(mesh.triangles)
    assert legacy.get_surface_area() == pytest.approx(mesh.triangle_areas().sum(), rel=1e-12)
    np.testing.assert_allclose(np.asarray(legacy.vertices), mesh.vertices)
    # Welding coincident vertices gives a closed box: every edge shared by two triangles.
    legacy.merge_close_vertices(1e-9)
    assert legacy.is_edge_manifold()
    assert len(legacy.get_non_manifold_edges(allow_boundary_edges=False)) == 0
