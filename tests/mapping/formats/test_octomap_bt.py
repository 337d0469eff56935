"""OctoMap .bt files: the real geb079 tree, round trips through pyoctomap, corrupt files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.band import extract_band
from mapping.errors import MapError
from mapping.formats.octomap_bt import (
    KEY_OFFSET,
    decode_bt,
    encode_bt,
    grid_from_bt,
    read_bt,
    write_bt,
)
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


DEPTH = 16
_FREE, _OCCUPIED, _INNER = 1, 2, 3


def _morton_keys(keys: np.ndarray) -> np.ndarray:
    """48-bit codes whose 3-bit digits, most significant first, are the child indices."""
    code = np.zeros(len(keys), dtype=np.int64)
    for bit in range(DEPTH):
        for axis in range(3):
            code |= ((keys[:, axis] >> bit) & 1) << (3 * bit + axis)
    return code


def reference_encode(cells: np.ndarray, occupied: np.ndarray) -> tuple[int, bytes]:
    """The tree's node count and stream as the encoder wrote them level by level in numpy
    until stop 50 (the reference the depth-first encoder must match byte for byte)."""
    codes = _morton_keys(np.asarray(cells, dtype=np.int64) + KEY_OFFSET)
    order = np.argsort(codes, kind="stable")
    codes = codes[order]
    states = np.where(occupied[order], _OCCUPIED, _FREE).astype(np.int64)
    # Prune bottom-up: 8 siblings that are all leaves in one state become their parent.
    leaf_codes: list[np.ndarray] = []
    leaf_states: list[np.ndarray] = []
    leaf_depths: list[np.ndarray] = []
    for depth in range(DEPTH, 0, -1):
        if depth == 1 or len(codes) == 0:
            final = np.ones(len(codes), dtype=bool)
        else:
            parents = codes >> 3
            starts = np.flatnonzero(np.r_[True, parents[1:] != parents[:-1]])
            sizes = np.diff(np.r_[starts, len(codes)])
            same = np.minimum.reduceat(states, starts) == np.maximum.reduceat(states, starts)
            merge_group = (sizes == 8) & same
            final = ~np.repeat(merge_group, sizes)
        leaf_codes.append(codes[final])
        leaf_states.append(states[final])
        leaf_depths.append(np.full(int(final.sum()), depth))
        if depth > 1 and len(codes):
            codes = parents[starts[merge_group]]
            states = states[starts[merge_group]]
    all_codes = np.concatenate(leaf_codes)
    all_states = np.concatenate(leaf_states)
    all_depths = np.concatenate(leaf_depths)
    if len(all_codes) == 0:
        return 0, b""
    # Inner nodes: every ancestor (depth 0 … d − 1) of every leaf; children's codes per node.
    inner_codes, inner_depths, inner_words = [], [], []
    children: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for depth in range(DEPTH - 1, -1, -1):
        deeper_leaf = all_depths == depth + 1
        child_codes = [all_codes[deeper_leaf]]
        child_values = [all_states[deeper_leaf]]
        if depth + 1 in children:
            child_codes.append(children[depth + 1][0])
            child_values.append(np.full(len(children[depth + 1][0]), _INNER))
        kids = np.concatenate(child_codes)
        values = np.concatenate(child_values)
        if len(kids) == 0:
            continue
        parents = kids >> 3
        unique, inverse = np.unique(parents, return_inverse=True)
        words = np.zeros(len(unique), dtype=np.int64)
        np.add.at(words, inverse, values << (2 * (kids & 7)))
        children[depth] = (unique, words)
        inner_codes.append(unique)
        inner_depths.append(np.full(len(unique), depth))
        inner_words.append(words)
    codes_all = np.concatenate(inner_codes)
    depths_all = np.concatenate(inner_depths)
    words_all = np.concatenate(inner_words)
    # Depth-first pre-order: sort by the code padded to full depth, ancestors first.
    padded = codes_all << (3 * (DEPTH - depths_all))
    preorder = np.lexsort((depths_all, padded))
    stream = words_all[preorder].astype("<u2").tobytes()
    return len(codes_all) + len(all_codes), stream


def split_encoded(data: bytes) -> tuple[int, bytes]:
    head, _, stream = data.partition(b"\ndata\n")
    return int(head.split(b"\nsize ")[1].split(b"\n")[0]), stream


@st.composite
def cell_sets(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray]:
    """Unique cells in a few clusters (so that whole octants fill and prune), some anywhere in
    OctoMap's key range, with random or uniform states."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    parts = []
    for _ in range(draw(st.integers(0, 4))):
        edge = draw(st.sampled_from([1, 2, 4, 8, 16]))
        corner = rng.integers(-40, 40, 3) * draw(st.sampled_from([1, 2, 8]))
        cube = np.stack(np.meshgrid(*[np.arange(edge)] * 3, indexing="ij"), -1).reshape(-1, 3)
        keep = rng.random(len(cube)) < draw(st.sampled_from([1.0, 0.97, 0.5]))
        parts.append(corner + cube[keep])
    parts.append(rng.integers(-KEY_OFFSET, KEY_OFFSET, (draw(st.integers(0, 30)), 3)))
    cells = np.unique(np.concatenate(parts), axis=0)
    cells = cells[rng.permutation(len(cells))]
    mode = draw(st.sampled_from(["random", "free", "occupied", "by_octant"]))
    if mode == "random":
        occupied = rng.random(len(cells)) < 0.3
    elif mode == "by_octant":
        occupied = (cells // 4).sum(axis=1) % 2 == 0
    else:
        occupied = np.full(len(cells), mode == "occupied")
    return cells, occupied


@settings(max_examples=300, deadline=None)
@given(cell_sets())
def test_the_encoder_matches_the_level_by_level_reference(
    cells_states: tuple[np.ndarray, np.ndarray],
) -> None:
    cells, occupied = cells_states
    size, stream = split_encoded(encode_bt(cells, occupied, 0.1))
    assert (size, stream) == reference_encode(cells, occupied)
    # And it reads back to the same cells and states.
    back, states = decode_bt(encode_bt(cells, occupied, 0.1)).expand()
    order, back_order = np.lexsort(cells.T), np.lexsort(back.T)
    np.testing.assert_array_equal(back[back_order], cells[order])
    np.testing.assert_array_equal(states[back_order], occupied[order])


def test_the_encoder_prunes_whole_octants_up_to_below_the_root() -> None:
    # A full cube of 2^5 cells a side, all free: one leaf at depth 11, inside 11 inner nodes.
    cube = np.stack(np.meshgrid(*[np.arange(32)] * 3, indexing="ij"), -1).reshape(-1, 3)
    size, stream = split_encoded(encode_bt(cube, np.zeros(len(cube), bool), 0.1))
    assert (size, len(stream)) == (12, 22)
    tree = decode_bt(encode_bt(cube, np.zeros(len(cube), bool), 0.1))
    assert tree.depth.tolist() == [11]
    assert not tree.occupied[0]
    # One cell occupied: its octants split down to single cells: 16 inner nodes, 7 leaves
    # beside each of the 4 split octants below depth 11 and the 8 cells of the last.
    states = np.zeros(len(cube), bool)
    states[0] = True
    size, _ = split_encoded(encode_bt(cube, states, 0.1))
    assert size == reference_encode(cube, states)[0] == 16 + 4 * 7 + 8


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
