"""OctoMap's binary tree files (``.bt``): read and write, so maps open in OctoMap's tools.

A ``.bt`` file is a few ASCII header lines — ``# Octomap OcTree binary file``, then ``id``,
``size`` (the number of tree nodes), ``res`` (the leaf edge in metres) and ``data`` — followed
by the octree as a depth-first bit stream: each inner node is 2 bytes holding 2 bits per child
(children 0–3 in the first byte, 4–7 in the second; bits 2j and 2j + 1 for child j mod 4):
(1, 0) a free leaf, (0, 1) an occupied leaf, (1, 1) an inner node whose own 2 bytes follow
(children in order, depth first), (0, 0) unknown. Child index bits 0, 1, 2 set the x, y, z key
bit at that depth; the tree is 16 levels deep and keys are offset by 2^15, so a cell index i of
a grid whose origin is 0 is key i + 32768, and a leaf at depth d is a cube of 2^(16 − d) cells.

The format keeps only occupied/free per leaf (OctoMap reads occupied leaves at its upper
clamping bound and free ones at its lower): it is lossy, which is why it is smaller than
``map.npz``. Writing merges 8 equal leaves into their parent as OctoMap's pruning does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit

from mapping.errors import MapError
from mapping.grid import GridParams, OccupancyGrid
from sensors.atomic import atomic_path
from sensors.yamlio import read_file_bytes

__all__ = [
    "BT_HEADER",
    "BtTree",
    "decode_bt",
    "encode_bt",
    "grid_from_bt",
    "read_bt",
    "tree_stream",
    "write_bt",
]

BT_HEADER = "# Octomap OcTree binary file"
TREE_DEPTH = 16
KEY_OFFSET = 1 << (TREE_DEPTH - 1)
#: The most cells ``BtTree.expand`` produces (about 1.6 GB of cell indices); geb079, a whole
#: building at 5 cm, covers 1.1 M.
MAX_EXPANDED_CELLS = 1 << 26
_FREE, _OCCUPIED, _INNER = 1, 2, 3
_MAX_HEADER_BYTES = 4096
#: The largest ``.bt`` file read (2 bytes per inner node: half a billion nodes); geb079 is 209 kB.
BT_LIMIT_BYTES = 2**30


@dataclass(frozen=True)
class BtTree:
    """The leaves of an OctoMap tree.

    ``keys`` (L, 3) int64 are the keys of each leaf's lowest corner cell, ``depth`` (L,) the
    leaf's depth (16 = one cell), ``occupied`` (L,) its state.
    """

    resolution_m: float
    tree_id: str
    keys: np.ndarray
    depth: np.ndarray
    occupied: np.ndarray
    node_count: int

    def __len__(self) -> int:
        return len(self.depth)

    @property
    def edge_cells(self) -> np.ndarray:
        """(L,) leaf edges in cells."""
        return np.asarray(1 << (TREE_DEPTH - self.depth.astype(np.int64)))

    def centers(self) -> np.ndarray:
        """(L, 3) leaf centres in metres (OctoMap's coordinates)."""
        half = self.edge_cells[:, None] / 2.0
        return np.asarray((self.keys - KEY_OFFSET + half) * self.resolution_m)

    def cell_count(self, z_range_cells: tuple[int, int] | None = None) -> int:
        """How many cells the leaves cover (within the layers of ``z_range_cells``)."""
        edge = self.edge_cells.astype(np.int64)
        layers = edge
        if z_range_cells is not None:
            low = self.keys[:, 2].astype(np.int64) - KEY_OFFSET
            top = np.minimum(low + edge - 1, z_range_cells[1])
            layers = np.clip(top - np.maximum(low, z_range_cells[0]) + 1, 0, None)
        return int(np.sum(edge * edge * layers, dtype=np.float64))

    def expand(self, z_range_cells: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every cell the leaves cover: (N, 3) cell indices (key − 32768) and (N,) occupied.

        ``z_range_cells`` (k_first, k_last) keeps only the cells of those layers. A tree whose
        leaves cover more than ``MAX_EXPANDED_CELLS`` cells is refused before anything is
        allocated (a few bytes of crafted tree can declare leaves of 2^45 cells).
        """
        count = self.cell_count(z_range_cells)
        if count > MAX_EXPANDED_CELLS:
            raise MapError(
                f"the tree's leaves cover {count:,} cells, more than the {MAX_EXPANDED_CELLS:,} "
                "coopmap expands (coarse leaves of a huge or crafted tree)"
            )
        cells, states = [], []
        for d in np.unique(self.depth):
            pick = self.depth == d
            edge = 1 << (TREE_DEPTH - int(d))
            lows = self.keys[pick] - KEY_OFFSET
            occupied = self.occupied[pick]
            zs = np.arange(edge)
            if z_range_cells is not None:
                k_first, k_last = z_range_cells
                overlap = (lows[:, 2] + edge - 1 >= k_first) & (lows[:, 2] <= k_last)
                lows, occupied = lows[overlap], occupied[overlap]
            grid = np.stack(np.meshgrid(zs, zs, zs, indexing="ij"), axis=-1).reshape(-1, 3)
            expanded = (lows[:, None, :] + grid[None]).reshape(-1, 3)
            flags = np.repeat(occupied, len(grid))
            if z_range_cells is not None:
                keep = (expanded[:, 2] >= z_range_cells[0]) & (expanded[:, 2] <= z_range_cells[1])
                expanded, flags = expanded[keep], flags[keep]
            cells.append(expanded)
            states.append(flags)
        if not cells:
            return np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=bool)
        return np.concatenate(cells).astype(np.int64), np.concatenate(states)


@njit(cache=True)
def _decode_stream(data: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int, int]:
    """Walk the bit stream: (keys, depth, occupied, leaves, inner nodes, status).

    status ≥ 0: the number of bytes used; −1 − pos: truncated at byte pos; −100000000 − pos:
    an inner node below the deepest level at byte pos.
    """
    capacity = 4 * len(data) + 8
    keys = np.empty((capacity, 3), dtype=np.int64)
    depth = np.empty(capacity, dtype=np.int8)
    occupied = np.empty(capacity, dtype=np.bool_)
    words = np.zeros(TREE_DEPTH + 1, dtype=np.int64)
    child = np.zeros(TREE_DEPTH + 1, dtype=np.int64)
    node_key = np.zeros((TREE_DEPTH + 1, 3), dtype=np.int64)
    leaves = 0
    inner = 0
    if len(data) < 2:
        return keys[:0], depth[:0], occupied[:0], 0, 0, -1
    words[0] = np.int64(data[0]) | (np.int64(data[1]) << 8)
    pos = 2
    inner = 1
    level = 0
    # Leaves of the node at `level` are recorded on entry; inner children are entered in order.
    for c in range(8):
        code = (words[0] >> (2 * c)) & 3
        if 0 < code < _INNER:
            bit = 1 << (TREE_DEPTH - 1)
            keys[leaves, 0] = bit if c & 1 else 0
            keys[leaves, 1] = bit if c & 2 else 0
            keys[leaves, 2] = bit if c & 4 else 0
            depth[leaves] = 1
            occupied[leaves] = code == _OCCUPIED
            leaves += 1
    while level >= 0:
        if child[level] == 8:
            level -= 1
            continue
        c = child[level]
        child[level] += 1
        if (words[level] >> (2 * c)) & 3 != _INNER:
            continue
        if level + 1 >= TREE_DEPTH:
            return keys[:leaves], depth[:leaves], occupied[:leaves], leaves, inner, -100000000 - pos
        if pos + 2 > len(data):
            return keys[:leaves], depth[:leaves], occupied[:leaves], leaves, inner, -1 - pos
        bit = 1 << (TREE_DEPTH - 1 - level)
        for axis in range(3):
            node_key[level + 1, axis] = node_key[level, axis] | (bit if (c >> axis) & 1 else 0)
        level += 1
        words[level] = np.int64(data[pos]) | (np.int64(data[pos + 1]) << 8)
        child[level] = 0
        pos += 2
        inner += 1
        child_bit = 1 << (TREE_DEPTH - 1 - level)
        for cc in range(8):
            code = (words[level] >> (2 * cc)) & 3
            if 0 < code < _INNER:
                for axis in range(3):
                    keys[leaves, axis] = node_key[level, axis] | (
                        child_bit if (cc >> axis) & 1 else 0
                    )
                depth[leaves] = level + 1
                occupied[leaves] = code == _OCCUPIED
                leaves += 1
    return keys[:leaves], depth[:leaves], occupied[:leaves], leaves, inner, pos


def _parse_header(data: bytes, source: str) -> tuple[str, int, float, int]:
    """(id, size, res, offset of the bit stream)."""
    if not data.startswith(BT_HEADER.encode("ascii")):
        raise MapError(f"{source}: not an OctoMap binary file (first line is not {BT_HEADER!r})")
    tree_id: str | None = None
    size: int | None = None
    res: float | None = None
    pos = data.index(b"\n") + 1 if b"\n" in data else len(data)
    while True:
        end = data.find(b"\n", pos, pos + _MAX_HEADER_BYTES)
        if end < 0:
            raise MapError(f"{source}: truncated or malformed header (no 'data' line)")
        line = data[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        keyword = words[0]
        if keyword == "data":
            break
        if len(words) < 2:
            raise MapError(f"{source}: malformed header line {line!r} (no value)")
        try:
            if keyword == "id":
                tree_id = words[1]
            elif keyword == "size":
                size = int(words[1])
            elif keyword == "res":
                res = float(words[1])
        except ValueError:
            raise MapError(f"{source}: bad header value in {line!r}") from None
    if tree_id is None or size is None or res is None:
        raise MapError(f"{source}: header lacks id, size or res")
    if size < 0:
        raise MapError(f"{source}: negative tree size {size}")
    if not (math.isfinite(res) and res > 0):
        raise MapError(f"{source}: resolution must be positive, got {res}")
    return tree_id, size, res, pos


def tree_stream(data: bytes, source: str = "<bytes>") -> tuple[str, float, bytes]:
    """(tree id, resolution in m, the node stream) of ``.bt`` bytes: the stream without the
    header is what an ``octomap_msgs/Octomap`` message carries in ``data`` (``binary: true``)."""
    tree_id, _, resolution_m, offset = _parse_header(data, source)
    return tree_id, resolution_m, data[offset:]


def decode_bt(data: bytes, source: str = "<bytes>") -> BtTree:
    """Decode the bytes of a ``.bt`` file; MapError (naming ``source``) when malformed."""
    tree_id, size, res, offset = _parse_header(data, source)
    if size == 0:
        empty = np.zeros((0, 3), dtype=np.int64)
        return BtTree(res, tree_id, empty, np.zeros(0, np.int8), np.zeros(0, bool), 0)
    stream = np.frombuffer(data, dtype=np.uint8, offset=offset)
    keys, depth, occupied, leaves, inner, status = _decode_stream(stream)
    if status <= -100000000:
        raise MapError(
            f"{source}: corrupt tree: an inner node below depth {TREE_DEPTH} at byte "
            f"{offset - 100000000 - status}"
        )
    if status < 0:
        raise MapError(
            f"{source}: truncated: the tree needs more than the {len(stream)} bytes after the "
            f"header (stopped at byte {offset - 1 - status})"
        )
    if leaves + inner != size:
        raise MapError(
            f"{source}: corrupt tree: the header says {size} nodes, the data holds {leaves + inner}"
        )
    return BtTree(res, tree_id, keys, depth.astype(np.int8), occupied, leaves + inner)


def read_bt(path: Path | str) -> BtTree:
    """Read an OctoMap ``.bt`` file (a regular file of at most ``BT_LIMIT_BYTES``)."""
    path = Path(path)
    if not path.exists():
        raise MapError(f"{path}: cannot read: no such file")
    return decode_bt(read_file_bytes(path, MapError, BT_LIMIT_BYTES), str(path))


def encode_bt(cells: np.ndarray, occupied: np.ndarray, resolution_m: float) -> bytes:
    """The ``.bt`` bytes of (N, 3) unique cells (indices on a lattice anchored at 0) with their
    occupied/free states; 8 equal sibling leaves are merged into their parent (OctoMap's
    pruning).

    The cells are sorted by their Morton codes, each with its state in its two lowest bits
    (one int64 a cell), and the tree is written from them in one depth-first pass: 8 bytes a
    cell besides the stream, where sorting and pruning level by level in numpy took 114
    (a 789 k-cell map: 90 MB, at the peak of ``coopmap batch`` on office_loop)."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    occupied = np.asarray(occupied, dtype=bool).reshape(-1)
    if len(occupied) != len(cells):
        raise MapError(f"need one state per cell: {len(occupied)} for {len(cells)}")
    if not (math.isfinite(resolution_m) and resolution_m > 0):
        raise MapError(f"resolution must be positive, got {resolution_m!r}")
    if len(cells) == 0:
        return _header("OcTree", 0, resolution_m)
    packed = np.empty(len(cells), dtype=np.int64)
    if not _packed_codes(cells, occupied, packed):
        raise MapError(
            f"cells beyond OctoMap's ±{KEY_OFFSET} cells from the origin cannot be written"
        )
    packed.sort()
    words, size = _tree_stream(packed)
    if size < 0:
        raise MapError("cells are not unique")
    stream = words.astype("<u2", copy=False).tobytes()
    return _header("OcTree", size, resolution_m) + stream


@njit(cache=True, nogil=True)
def _packed_codes(cells: np.ndarray, occupied: np.ndarray, packed: np.ndarray) -> bool:
    """Each cell's key's Morton code (its 3-bit digits, most significant first, the child
    indices from the root down: bit b of axis a at 3b + a) shifted up by two, its state
    (``_FREE`` or ``_OCCUPIED``) in the two bits below, into ``packed``; False when a cell's key
    lies outside OctoMap's 16 bits."""
    for i in range(len(cells)):
        code = 0
        for axis in range(3):
            key = cells[i, axis] + KEY_OFFSET
            if key < 0 or key >= 2 * KEY_OFFSET:
                return False
            for bit in range(TREE_DEPTH):
                code |= ((key >> bit) & 1) << (3 * bit + axis)
        packed[i] = (code << 2) | (_OCCUPIED if occupied[i] else _FREE)
    return True


@njit(cache=True, nogil=True)
def _tree_stream(packed: np.ndarray) -> tuple[np.ndarray, int]:
    """The inner nodes' words in depth-first pre-order, and the tree's node count (−1 when two
    cells share a code), from the sorted ``packed`` codes.

    A node's word is reserved before its children are written; a node whose 8 children all
    came back as leaves of one state is taken back out (its word and nothing else: leaves have
    no words) and becomes a leaf of that state in its parent, OctoMap's pruning. The root stays
    an inner node."""
    n = len(packed)
    for i in range(1, n):
        if packed[i] >> 2 == packed[i - 1] >> 2:
            return np.zeros(0, dtype=np.uint16), -1
    words = np.empty(max(n // 4, 64), dtype=np.uint16)
    top = 1  # words written: the root's is reserved
    nodes = 0  # inner nodes and leaves in the written words
    # Per depth: the node's range end, its next child's first code, the next child's digit,
    # where its word is, the word, children present, children that are leaves, and their
    # common state (0 none yet, _INNER once they differ or one is inner).
    end = np.zeros(TREE_DEPTH, dtype=np.int64)
    cursor = np.zeros(TREE_DEPTH, dtype=np.int64)
    digit = np.zeros(TREE_DEPTH, dtype=np.int64)
    at = np.zeros(TREE_DEPTH, dtype=np.int64)
    word = np.zeros(TREE_DEPTH, dtype=np.int64)
    kids = np.zeros(TREE_DEPTH, dtype=np.int64)
    leaves = np.zeros(TREE_DEPTH, dtype=np.int64)
    common = np.zeros(TREE_DEPTH, dtype=np.int64)
    d = 0
    end[0] = n
    while True:
        if digit[d] == 8:  # the node at depth d is complete
            if d > 0 and kids[d] == 8 and common[d] != _INNER:
                kind = common[d]
                top = at[d]  # pruned: its word taken back
            else:
                kind = _INNER
                words[at[d]] = word[d]
                nodes += 1 + leaves[d]
            if d == 0:
                break
            d -= 1
        else:
            shift = 2 + 3 * (TREE_DEPTH - 1 - d)  # the child's digit, past the state's bits
            first = cursor[d]
            last = first
            while last < end[d] and (packed[last] >> shift) & 7 == digit[d]:
                last += 1
            cursor[d] = last
            if first == last:
                digit[d] += 1
                continue
            if d + 1 < TREE_DEPTH:  # an inner child: its subtree first
                if top == len(words):
                    grown = np.empty(2 * len(words), dtype=np.uint16)
                    grown[:top] = words[:top]
                    words = grown
                d += 1
                end[d], cursor[d], digit[d], at[d] = last, first, 0, top
                word[d] = kids[d] = leaves[d] = common[d] = 0
                top += 1
                continue
            kind = packed[first] & 3  # a cell at the deepest level
        # The child (digit[d]) of the node at depth d is ``kind``.
        word[d] |= kind << (2 * digit[d])
        kids[d] += 1
        if kind != _INNER:
            leaves[d] += 1
        if common[d] == 0:
            common[d] = kind
        elif common[d] != kind:
            common[d] = _INNER
        digit[d] += 1
    return words[:top], nodes


def _header(tree_id: str, size: int, resolution_m: float) -> bytes:
    return (
        f"{BT_HEADER}\n# (feel free to add / change comments, but leave the first line as it "
        f"is!)\n#\n# written by coopmap\nid {tree_id}\nsize {size}\nres {resolution_m!r}\ndata\n"
    ).encode("ascii")


def write_bt(path: Path | str, grid: OccupancyGrid, threshold: float | None = None) -> Path:
    """Write the known cells of ``grid`` as an OctoMap ``.bt`` (occupied: P > ``threshold``,
    default the grid's), atomically. The grid's lattice must be OctoMap's (origin 0)."""
    path = Path(path)
    if any(v != 0.0 for v in grid.params.origin_m):
        raise MapError(
            f"{path}: OctoMap's lattice has its corner at the origin; this grid's is at "
            f"{list(grid.params.origin_m)}"
        )
    cells, values = grid.cells()
    if threshold is None:
        level = grid.params.logodds_threshold
    else:
        level = float(np.log(threshold / (1.0 - threshold)))
    data = encode_bt(cells, values > level, grid.resolution_m)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def grid_from_bt(
    tree: BtTree,
    params: GridParams | None = None,
    *,
    z_range_m: tuple[float, float] | None = None,
) -> OccupancyGrid:
    """An occupancy grid holding the tree's leaves, cell by cell, as OctoMap reads them:
    occupied leaves at the upper clamping bound, free ones at the lower.

    ``params`` supplies the sensor model and clamping (default: OctoMap's); its resolution is
    replaced by the tree's and its origin must be 0. ``z_range_m`` (z_min, z_max) keeps only the
    layers whose cell centres lie within [z_min, z_max) — a band without the whole building.
    """
    from dataclasses import replace

    from mapping.band import band_layers

    params = GridParams() if params is None else params
    if any(v != 0.0 for v in params.origin_m):
        raise MapError("a grid read from a .bt file has its lattice corner at the origin")
    params = replace(params, resolution_m=tree.resolution_m)
    z_range = None
    if z_range_m is not None:
        z_range = band_layers(0.0, tree.resolution_m, *z_range_m)
    cells, occupied = tree.expand(z_range)
    values = np.where(occupied, params.logodds_max, params.logodds_min)
    return OccupancyGrid.from_cells(params, cells, values)
