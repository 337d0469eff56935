"""2D bands: summing columns over a height band, against hand counts and the world's truth."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mapping.band import Band, CeilingRule, band_layers, extract_band, extract_ceiling_band
from mapping.errors import MapError
from mapping.figures import render_band
from mapping.grid import GridParams, OccupancyGrid
from sensors.sim.scene import build_mesh
from sensors.sim.truth import band_share, surface_voxels
from sensors.sim.world import world_from_mapping
from tests.mapping.conftest import room_scan


def synthetic_room() -> OccupancyGrid:
    """A 10 × 8 × 30 cell room (0.1 m): occupied walls on the outer ring of columns in every
    layer, free inside, a shelf (occupied) in layers 20–22 of column (4, 4), and a column (7, 5)
    that was never observed above layer 5."""
    params = GridParams()
    grid = OccupancyGrid(params)
    i, j, k = np.meshgrid(np.arange(10), np.arange(8), np.arange(30), indexing="ij")
    cells = np.column_stack([i.ravel(), j.ravel(), k.ravel()])
    wall = (cells[:, 0] % 9 == 0) | (cells[:, 1] % 7 == 0)
    shelf = (cells[:, 0] == 4) & (cells[:, 1] == 4) & (cells[:, 2] >= 20) & (cells[:, 2] <= 22)
    unseen = (cells[:, 0] == 7) & (cells[:, 1] == 5) & (cells[:, 2] > 5)
    keep = ~unseen
    evidence = np.where(wall | shelf, 0.9, 0.2)[keep]
    grid.apply_evidence(cells[keep], evidence)
    return grid


def test_band_layers_take_cell_centres_in_the_half_open_band() -> None:
    assert band_layers(0.0, 0.1, 2.3, 2.9) == (23, 28)  # centres 2.35 … 2.85
    assert band_layers(0.0, 0.08, 2.3, 2.55) == (29, 31)  # centres 2.36, 2.44, 2.52
    assert band_layers(0.0, 0.1, 2.35, 2.45) == (23, 23)  # a centre on the lower edge is in
    assert band_layers(0.05, 0.1, 0.0, 0.2) == (-1, 0)
    with pytest.raises(MapError, match="holds no cell centre"):
        band_layers(0.0, 0.1, 2.31, 2.34)
    with pytest.raises(MapError, match="must run upwards"):
        band_layers(0.0, 0.1, 2.9, 2.3)


def test_a_synthetic_room_band_sums_its_columns() -> None:
    band = extract_band(synthetic_room(), 1.95, 2.55)  # layers 20–25: six layers
    assert band.shape == (8, 10)
    np.testing.assert_allclose(band.lower_xy, [0.0, 0.0])
    expected = np.zeros((8, 10))
    expected[[0, 7], :] = 1.0
    expected[:, [0, 9]] = 1.0
    expected[4, 4] = 3 / 6  # the shelf fills three of the six layers
    np.testing.assert_allclose(band.occupancy, expected, atol=1e-15)
    known = np.ones((8, 10), bool)
    known[5, 7] = False
    np.testing.assert_array_equal(band.known, known)
    assert band.occupancy[5, 7] == 0.0
    low = extract_band(synthetic_room(), 0.0, 0.3)  # the floor layers see no shelf
    assert low.occupancy[4, 4] == 0.0
    assert low.known[5, 7]  # layers 0–2 of the column were observed
    higher = extract_band(synthetic_room(), 0.0, 3.0, threshold=0.95)
    assert higher.occupancy.max() == 0.0  # nothing is that sure


def test_a_rectangle_crops_or_pads_the_band() -> None:
    band = extract_band(synthetic_room(), 1.95, 2.55, lower_xy=(-0.25, 0.35), upper_xy=(0.55, 0.55))
    assert band.shape == (3, 9)
    np.testing.assert_allclose(band.lower_xy, [-0.3, 0.3])
    assert not band.known[:, :3].any()  # columns −3 … −1 lie outside the room
    np.testing.assert_allclose(band.occupancy[:, 3], 1.0)  # the x = 0 wall
    np.testing.assert_allclose(band.extent(), (-0.3, 0.6, 0.3, 0.6))
    x, y = band.cell_centers()
    assert x[0, 0] == pytest.approx(-0.25)
    assert y[0, 0] == pytest.approx(0.35)


def test_a_band_of_the_truth_equals_the_truth_band() -> None:
    # The occupied voxels of a world's surfaces, as a grid, give the ground-truth band image.
    doc = {
        "name": "r",
        "rooms": [{"name": "r", "footprint": [[0, 0], [4, 0], [4, 3], [0, 3]], "ceiling_m": 2.5}],
        "boxes": [{"name": "duct", "center": [2.0, 1.5], "size": [2.0, 0.4], "z_m": [2.1, 2.3]}],
    }
    truth = surface_voxels(build_mesh(world_from_mapping(doc)), 0.1)
    grid = OccupancyGrid()
    grid.apply_evidence(truth.indices, np.full(len(truth), 0.9))
    ours = extract_band(grid, 2.0, 2.45, lower_xy=(0.0, 0.0), upper_xy=(4.0, 3.0))
    expected = band_share(truth, 2.0, 2.45, np.array([0.0, 0.0]), np.array([4.0, 3.0]))
    np.testing.assert_allclose(ours.lower_xy, expected.lower_xy)
    np.testing.assert_allclose(ours.occupancy, expected.share, atol=1e-15)
    assert 0 < ours.occupancy.mean() < 1


def test_a_scanned_room_shows_its_walls_in_the_ceiling_band() -> None:
    sensor = np.array([2.013, 1.517, 0.45])
    grid = OccupancyGrid()
    grid.integrate_scan(room_scan(sensor), sensor)
    band = extract_band(grid, 2.0, 2.4)
    # Wall columns are occupied in every band layer they were seen in; the inside is free.
    inside = band.occupancy[3:-3, 3:-3]
    assert inside.max() == 0.0
    assert band.known[3:-3, 3:-3].mean() > 0.9
    assert band.occupancy[:, 0].mean() > 0.5
    assert band.occupancy[:, -1].mean() > 0.5


def test_a_column_seen_free_in_few_layers_is_unknown_with_free_min_observed() -> None:
    """Column (7, 5) was observed only below layer 6; the band 0.25–0.85 m (layers 2–7, six
    layers) sees four of its layers, all free. Layers 4–9 see two: with free_min_observed 0.5 the
    column is free in the first band and unknown in the second, as are never-observed columns;
    occupied columns stay known whatever the share."""
    grid = synthetic_room()
    low = extract_band(grid, 0.25, 0.85, free_min_observed=0.5)
    high = extract_band(grid, 0.45, 1.05, free_min_observed=0.5)
    default = extract_band(grid, 0.45, 1.05)
    assert low.known[5, 7]
    assert low.occupancy[5, 7] == 0.0
    assert not high.known[5, 7]
    assert default.known[5, 7]  # the docs/design.md's plain sum: free
    assert default.occupancy[5, 7] == 0.0
    assert high.known[0, :].all()  # a wall row
    assert (high.occupancy[0, :] == 1.0).all()
    assert high.known.sum() == default.known.sum() - 1
    every = extract_band(grid, 0.45, 1.05, free_min_observed=1.0)
    assert not every.known[5, 7]
    assert every.known.sum() == high.known.sum()
    for bad in (-0.1, 1.5, math.nan):
        with pytest.raises(MapError, match="free_min_observed must lie in"):
            extract_band(grid, 0.45, 1.05, free_min_observed=bad)


def test_a_band_tells_which_points_fall_on_its_known_cells() -> None:
    """Cells of 0.5 m from (1, 2): the point's cell must be known; points off the grid, NaN
    and infinite ones fall on none."""
    known = np.zeros((3, 4), dtype=bool)  # rows y, columns x
    known[1, 2] = known[0, 0] = True
    band = Band(np.zeros((3, 4)), known, np.array([1.0, 2.0]), 0.5)
    points = np.array([
        [2.2, 2.7],  # row 1, column 2: known
        [1.0, 2.0],  # the corner of cell (0, 0): known
        [1.6, 2.2],  # row 0, column 1: unknown
        [0.99, 2.2], [3.0, 2.2], [1.2, 3.5], [1.2, 1.9],  # just off each side
        [np.nan, 2.2], [np.inf, 2.2], [2.2, -np.inf],
    ])  # fmt: skip
    assert band.covers(points).tolist() == [True, True] + [False] * 8
    assert band.covers(np.zeros((0, 2))).shape == (0,)
    np.testing.assert_allclose(band.known_centers(), [[1.25, 2.25], [2.25, 2.75]])


def test_errors_name_the_problem() -> None:
    grid = synthetic_room()
    with pytest.raises(MapError, match=r"holds no observed cell"):
        extract_band(grid, 5.0, 6.0)
    with pytest.raises(MapError, match="empty rectangle"):
        extract_band(grid, 0.0, 1.0, lower_xy=(1.0, 1.0), upper_xy=(0.0, 2.0))
    with pytest.raises(MapError, match="must be equal 2D shapes"):
        Band(np.zeros((2, 3)), np.zeros((3, 2), bool), np.zeros(2), 0.1)
    with pytest.raises(MapError, match="resolution must be positive"):
        Band(np.zeros((2, 3)), np.zeros((2, 3), bool), np.zeros(2), 0.0)


def test_a_band_figure_is_drawn(tmp_path: Path) -> None:
    from matplotlib.image import imread

    path = render_band(extract_band(synthetic_room(), 1.95, 2.55), tmp_path / "band.png", title="t")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rgb = np.asarray(imread(path))[..., :3].reshape(-1, 3)
    assert (rgb.max(axis=1) < 0.2).mean() > 0.01  # the walls are drawn dark


def two_ceilings() -> OccupancyGrid:
    """Two rooms side by side as a scanner sees them, 0.1 m cells: a low office (columns
    i < 20, ceiling plane in layer 24, i.e. 2.4–2.5 m) with a luminaire hanging into layer 22
    at column (5, 5), and a high hall (i ≥ 20, roof in layer 39) with a truss in layers 33–35 at
    columns i = 30. Everything below each ceiling was seen free; nothing above it was seen.
    Column (10, 8) saw no ceiling (a cupboard top at layer 18 hid it)."""
    cells, evidence = [], []
    for i in range(40):
        for j in range(16):
            roof = 24 if i < 20 else 39
            for k in range(roof + 1):
                occupied = (
                    k == roof or ((i, j) == (5, 5) and k == 22) or (i == 30 and 33 <= k <= 35)
                )
                if (i, j) == (10, 8) and k > 18:
                    break
                cells.append((i, j, k))
                evidence.append(0.9 if occupied or ((i, j) == (10, 8) and k == 18) else 0.2)
    grid = OccupancyGrid(GridParams())
    grid.apply_evidence(np.array(cells), np.array(evidence))
    return grid


def test_a_ceiling_band_follows_each_rooms_ceiling() -> None:
    grid = two_ceilings()
    rule = CeilingRule(depth_m=0.6, gap_m=0.1, smooth_m=0.5, fallback_m=(2.3, 2.9))
    band = extract_ceiling_band(grid, rule)
    assert band.shape == (16, 40)
    assert band.known.all()
    # The office: layers 18–23 (1.8–2.4 m); the luminaire fills one of six, the ceiling none.
    office = band.occupancy[:, :20]
    assert office[5, 5] == pytest.approx(1 / 6)
    assert office.sum() == pytest.approx(1 / 6 + office[8, 10])
    # The hall: layers 33–38; the truss fills three of six, the free air around it nothing.
    hall = band.occupancy[:, 20:]
    np.testing.assert_allclose(hall[:, 10], 3 / 6)
    assert hall[:, [0, 5, 15, 19]].max() == 0.0
    # The column whose ceiling was hidden takes its neighbours' band: its cupboard top at
    # layer 18 lies in the band's lowest layer.
    assert office[8, 10] == pytest.approx(1 / 6)


def test_the_fixed_band_sees_only_ceilings_where_the_ceiling_band_sees_structure() -> None:
    grid = two_ceilings()
    fixed = extract_band(grid, 2.3, 2.9)  # layers 23–28
    # In the office it holds the ceiling plane in every column, in the hall nothing but air.
    assert fixed.occupancy[0, 0] == pytest.approx(1 / 6)
    assert fixed.occupancy[:, 20:].max() == 0.0


def test_a_ceiling_band_without_any_ceiling_falls_back_to_the_fixed_band() -> None:
    grid = synthetic_room()  # walls reach the top layer 29: the walls are its "ceiling"
    empty = OccupancyGrid(GridParams())
    free = np.array([(i, j, k) for i in range(5) for j in range(5) for k in range(30)])
    empty.apply_evidence(free, np.full(len(free), 0.2))
    rule = CeilingRule(fallback_m=(1.95, 2.55))
    band = extract_ceiling_band(empty, rule)
    np.testing.assert_array_equal(band.occupancy, extract_band(empty, 1.95, 2.55).occupancy)
    assert extract_ceiling_band(grid, rule).known.any()


def test_ceiling_band_errors_are_one_line() -> None:
    with pytest.raises(MapError, match="depth_m must be positive"):
        CeilingRule(depth_m=0.0)
    with pytest.raises(MapError, match="gap_m must be a finite length"):
        CeilingRule(gap_m=math.nan)
    with pytest.raises(MapError, match="grid is empty"):
        extract_ceiling_band(OccupancyGrid(GridParams()), CeilingRule())
    with pytest.raises(MapError, match="free_min_observed"):
        extract_ceiling_band(two_ceilings(), CeilingRule(), free_min_observed=2.0)
    with pytest.raises(MapError, match="empty rectangle"):
        extract_ceiling_band(two_ceilings(), CeilingRule(), lower_xy=(1, 1), upper_xy=(0, 0))
