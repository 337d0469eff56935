"""OctoMap .bt files: the real geb079 tree, round trips through pyoctomap, corrupt files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mapping.band import extract_band
from mapping.errors import MapError
from mapping.formats.octomap_bt import decode_bt, encode_bt, grid_from_bt, read_bt, write_bt
from mapping.grid import GridParams, OccupancyGrid
from tests.mapping.conftest import FR079, requires_fr079, room_scan

pyoctomap = pytest.importorskip("pyoctomap")
GEB079 = FR079 / "geb079.bt"


@pytest.fixture(scope="module")
def geb079() -> object:
    if not GEB079.is_file():
        pytest.skip("../shared/data/octomap_fr079 is absent")
    return read_bt(GEB079)


def scanned_grid() -> OccupancyGrid:
    grid = OccupancyGrid()
    for sensor in ([2.013, 1.517, 1.0], [1.2, 2.2, 0.5]):
        grid.integrate_scan(room_scan(np.array(sensor)), np.array(sensor))
    return grid


def peer_leaves(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centres, sizes, occupied) of the leaves of a .bt file as OctoMap reads it."""
    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(path))
    rows = [
        (*leaf.getCoordinate(), leaf.getSize(), tree.isNodeOccupied(leaf.current_node))
        for leaf in tree.begin_leafs()
    ]
    table = np.array(rows, dtype=np.float64).reshape(-1, 5)
    return table[:, :3], table[:, 3], table[:, 4].astype(bool)


def key_order(centers: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    return np.lexsort(np.column_stack([np.round(centers, 4), np.round(sizes, 4)]).T)


@requires_fr079
def test_geb079_decodes_to_its_published_counts(geb079: object) -> None:
    tree = geb079
    assert tree.resolution_m == 0.08
    assert int(tree.occupied.sum()) == 143_729
    assert int((~tree.occupied).sum()) == 284_415
    assert tree.node_count == 532_566
    assert int((tree.edge_cells[tree.occupied] ** 3).sum()) == 185_673
    centers = tree.centers()[tree.occupied]
    np.testing.assert_allclose(centers.min(axis=0), [-7.96, -7.48, -0.28], atol=1e-9)
    np.testing.assert_allclose(centers.max(axis=0), [30.92, 7.40, 2.76], atol=1e-9)


@requires_fr079
def test_geb079_leaves_are_octomaps_leaves(geb079: object) -> None:
    tree = geb079
    centers, sizes, occupied = peer_leaves(GEB079)
    ours = key_order(tree.centers(), tree.edge_cells * tree.resolution_m)
    theirs = key_order(centers, sizes)
    np.testing.assert_allclose(tree.centers()[ours], centers[theirs], atol=1e-4)
    np.testing.assert_array_equal(tree.occupied[ours], occupied[theirs])


@requires_fr079
def test_geb079_encodes_back_to_the_same_bytes(geb079: object) -> None:
    cells, occupied = geb079.expand()
    data = encode_bt(cells, occupied, geb079.resolution_m)
    original = GEB079.read_bytes()
    assert data[data.index(b"\ndata\n") + 6 :] == original[original.index(b"\ndata\n") + 6 :]
    assert b"size 532566\n" in data


@requires_fr079
def test_geb079_ceiling_band_occupied_cells(geb079: object) -> None:
    # The corridor outline: 2.30–2.55 m at 0.08 m (cell centres 2.36, 2.44, 2.52).
    band = extract_band(grid_from_bt(geb079, z_range_m=(2.3, 2.55)), 2.3, 2.55)
    occupied_columns = int((band.occupancy > 0).sum())
    # The decoder's own figure, counted straight from the occupied leaves.
    cells, occupied = geb079.expand(z_range_cells=(29, 31))
    expected = len(np.unique(cells[occupied][:, :2], axis=0))
    assert occupied_columns == expected == 6_554
    # And OctoMap's own reading of the file (pyoctomap's leaves, expanded) agrees.
    centers, sizes, peer_occupied = peer_leaves(GEB079)
    columns = set()
    for center, size in zip(centers[peer_occupied], sizes[peer_occupied], strict=True):
        edge = round(size / 0.08)
        steps = (np.arange(edge) - (edge - 1) / 2) * 0.08
        for z in center[2] + steps:
            if 2.3 <= z < 2.55:
                columns.update(
                    (int(np.floor(x / 0.08)), int(np.floor(y / 0.08)))
                    for x in center[0] + steps
                    for y in center[1] + steps
                )
    assert len(columns) == occupied_columns
    assert round(band.occupancy.sum() * 3) == int(occupied.sum())
    assert band.known.sum() > 3 * occupied_columns  # observed free space around the walls


def test_pyoctomap_reads_what_we_write(tmp_path: Path) -> None:
    grid = scanned_grid()
    path = write_bt(tmp_path / "room.bt", grid)
    centers, sizes, occupied = peer_leaves(path)
    tree = read_bt(path)
    assert len(centers) == len(tree)
    # Every known cell of the grid is in OctoMap's tree with the same state.
    cells, values = grid.cells()
    edges = np.rint(sizes / 0.1).astype(int)
    lows = np.floor(centers / 0.1 - edges[:, None] / 2 + 0.5).astype(int)
    state = {}
    for low, edge, occ in zip(lows, edges, occupied, strict=True):
        grid_axes = [np.arange(edge)] * 3
        for offset in np.stack(np.meshgrid(*grid_axes, indexing="ij"), -1).reshape(-1, 3):
            state[tuple(low + offset)] = occ
    assert len(state) == len(cells)
    assert all(state[tuple(c)] == (v > 0) for c, v in zip(cells, values, strict=True))


def test_we_read_what_pyoctomap_writes(tmp_path: Path) -> None:
    peer = pyoctomap.OcTree(0.1)
    rng = np.random.default_rng(1)
    peer.insertPointCloud(rng.normal(0, 2.0, (2000, 3)), np.array([0.3, -0.2, 0.1]))
    path = tmp_path / "peer.bt"
    assert peer.writeBinary(str(path))
    tree = read_bt(path)
    centers, sizes, occupied = peer_leaves(path)
    ours = key_order(tree.centers(), tree.edge_cells * tree.resolution_m)
    theirs = key_order(centers, sizes)
    np.testing.assert_allclose(tree.centers()[ours], centers[theirs], atol=1e-4)
    np.testing.assert_array_equal(tree.occupied[ours], occupied[theirs])


def test_grid_to_bt_to_grid_keeps_every_state(tmp_path: Path) -> None:
    grid = scanned_grid()
    params = GridParams()
    back = grid_from_bt(read_bt(write_bt(tmp_path / "room.bt", grid)), params)
    cells, values = grid.cells()
    read = back.logodds_at(cells)
    expected = np.where(values > 0, params.logodds_max, params.logodds_min)
    np.testing.assert_allclose(read, expected)
    assert back.known_count() == grid.known_count()
    # 8 equal siblings were merged into parents: fewer leaves than cells.
    assert len(read_bt(tmp_path / "room.bt")) < 0.5 * len(cells)


def test_empty_maps_round_trip(tmp_path: Path) -> None:
    tree = read_bt(write_bt(tmp_path / "empty.bt", OccupancyGrid()))
    assert len(tree) == 0
    assert tree.node_count == 0
    assert grid_from_bt(tree).known_count() == 0


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d.replace(b"# Octomap", b"# Nonsense"), "not an OctoMap binary file"),
        (lambda d: d.replace(b"\ndata\n", b"\n"), r"malformed header"),
        (lambda d: d.replace(b"res 0.1", b"res abc"), r"bad header value in 'res abc'"),
        (lambda d: d.replace(b"res 0.1", b"res -0.1"), "resolution must be positive"),
        (lambda d: d.replace(b"id OcTree\n", b""), "header lacks id, size or res"),
        (lambda d: d[: len(d) - 40], r"truncated: the tree needs more than"),
        (lambda d: d.replace(b"size ", b"size 1"), r"the header says 1\d+ nodes, the data holds"),
        (lambda d: d + b"", None),
    ],
)
def test_corrupt_files_are_clear_errors(
    tmp_path: Path, mutate: object, message: str | None
) -> None:
    good = write_bt(tmp_path / "room.bt", scanned_grid()).read_bytes()
    bad = tmp_path / "bad.bt"
    bad.write_bytes(mutate(good))  # type: ignore[operator]
    if message is None:
        assert len(read_bt(bad)) == len(decode_bt(good))
        return
    with pytest.raises(MapError, match=message):
        read_bt(bad)


def test_flipped_bits_are_caught(tmp_path: Path) -> None:
    good = write_bt(tmp_path / "room.bt", scanned_grid()).read_bytes()
    start = good.index(b"\ndata\n") + 6
    rng = np.random.default_rng(2)
    outcomes = []
    for _ in range(50):
        data = bytearray(good)
        data[start + int(rng.integers(0, len(good) - start))] ^= 1 << int(rng.integers(0, 8))
        try:
            decode_bt(bytes(data))
            outcomes.append("decoded")
        except MapError as error:
            outcomes.append(str(error))
    # A flipped child code adds, drops or nests a node: the node count no longer matches.
    errors = [o for o in outcomes if o != "decoded"]
    assert len(errors) >= 45
    assert all("corrupt tree" in e or "truncated" in e for e in errors)


def test_other_errors(tmp_path: Path) -> None:
    with pytest.raises(MapError, match=r"absent\.bt: cannot read"):
        read_bt(tmp_path / "absent.bt")
    shifted = OccupancyGrid(GridParams(origin_m=(0.05, 0.0, 0.0)))
    with pytest.raises(MapError, match="OctoMap's lattice has its corner at the origin"):
        write_bt(tmp_path / "x.bt", shifted)
    with pytest.raises(MapError, match="cannot be written"):
        encode_bt(np.array([[40000, 0, 0]]), np.array([True]), 0.1)
    with pytest.raises(MapError, match="cells are not unique"):
        encode_bt(np.array([[1, 2, 3], [1, 2, 3]]), np.array([True, False]), 0.1)
    with pytest.raises(MapError, match=r"a grid read from a \.bt file"):
        grid_from_bt(read_bt(write_bt(tmp_path / "e.bt", OccupancyGrid())), shifted.params)
    (tmp_path / "x.bt").write_bytes(b"old")
    with pytest.raises(MapError):
        write_bt(tmp_path / "x.bt", shifted)
    assert (tmp_path / "x.bt").read_bytes() == b"old"


def test_a_tree_of_huge_leaves_is_refused_before_expanding() -> None:
    from mapping.formats.octomap_bt import KEY_OFFSET, MAX_EXPANDED_CELLS, BtTree

    # Eight occupied leaves at depth 2: each a cube of 2^14 cells a side (2^42 cells), which a
    # few bytes of .bt declare.
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]) << 14
    tree = BtTree(0.1, "OcTree", corners, np.full(8, 2, dtype=np.int8), np.ones(8, bool), 9)
    assert tree.cell_count() == 8 * (1 << 42)
    with pytest.raises(MapError, match=r"leaves cover 35,184,372,088,832 cells, more than the"):
        tree.expand()
    with pytest.raises(MapError, match="more than the"):
        grid_from_bt(tree)
    # A band of one layer through them is still far too much; one small leaf is fine.
    assert tree.cell_count((-1, -1)) == 4 * (1 << 28)  # cells are keys - KEY_OFFSET
    small = BtTree(0.1, "OcTree", np.array([[KEY_OFFSET] * 3]), np.array([14], np.int8),
                   np.ones(1, bool), 1)  # fmt: skip
    cells, occupied = small.expand()
    assert len(cells) == 64 == small.cell_count()
    assert occupied.all()
    assert small.cell_count() <= MAX_EXPANDED_CELLS
