"""coopmap's native map file, ``map.npz``: versioned, compressed and lossless.

A zip of numpy arrays (``numpy.savez_compressed``), readable without coopmap:

=====================  ======================================================================
``format``             the string ``coopmap.map``
``version``            format version (this module writes 2 and reads 1 and 2)
``resolution_m``       cell edge
``origin_m``           (3,) corner of cell (0, 0, 0)
``block_size_cells``   edge of a storage block
``prob_hit`` …         the sensor model and clamping: ``prob_hit``, ``prob_miss``, ``clamp_min``,
                       ``clamp_max``, ``occupied_threshold``, ``no_return_free_m``
``block_coords``       (B, 3) int64 block coordinates (block b covers cells
                       ``block_coords[b] · block_size_cells + [0, block_size_cells)³``)
``known``              (B, ⌈bs³/8⌉) uint8: bit j (little-endian bit order) of block b is set
                       when its cell j is known; cell j = (x, y, z) with j = (x·bs + y)·bs + z
``logodds``            (K,) float32 (version 2; float64 in version 1): the log-odds of the
                       known cells, block by block, in j order
=====================  ======================================================================

Values are stored exactly as the grid holds them (float32 since version 2), so a map
round-trips bit for bit. Version 1 files (float64, written before the grid stored float32) are
read with each value rounded to the nearest float32 inside the clamping bounds. Loading checks
the format, the version and every shape, and raises ``MapError`` naming the file and the
problem; writing is atomic (a crash never leaves a half-written map where the old one was).
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from mapping.errors import MapError
from mapping.grid import GridParams, OccupancyGrid
from sensors.atomic import atomic_path
from sensors.yamlio import regular_file

__all__ = [
    "MAP_FORMAT",
    "MAP_VERSION",
    "MAX_DENSE_CELLS",
    "MAX_SPARSITY",
    "SMALL_MAP_CELLS",
    "load_map",
    "save_map",
]

MAP_FORMAT = "coopmap.map"
MAP_VERSION = 2
#: The log-odds type of each version this module reads.
_LOGODDS_TYPES: dict[int, np.dtype[Any]] = {1: np.dtype(np.float64), 2: np.dtype(np.float32)}
#: The most cells a loaded map's blocks may hold (1 GiB of float32 log-odds).
MAX_DENSE_CELLS = 2**28
#: Blocks beyond this many cells must be at least 1/MAX_SPARSITY known (maps coopmap writes
#: are about 1/3 known: rays fill the blocks they cross).
SMALL_MAP_CELLS = 2**24
MAX_SPARSITY = 64
#: Room for an .npy header in a member's declared size.
_NPY_HEADER = 4096
_POPCOUNT = np.array([bin(v).count("1") for v in range(256)], dtype=np.uint8)
_PARAM_KEYS = (
    "resolution_m",
    "prob_hit",
    "prob_miss",
    "clamp_min",
    "clamp_max",
    "occupied_threshold",
    "no_return_free_m",
)
_KEYS = (
    "format",
    "version",
    *_PARAM_KEYS,
    "block_size_cells",
    "origin_m",
    "block_coords",
    "known",
    "logodds",
)


def save_map(path: Path | str, grid: OccupancyGrid) -> Path:
    """Write ``grid`` to ``path`` (atomically) and return the path."""
    path = Path(path)
    params = grid.params
    coords, known, values = grid.known_blocks()
    arrays: dict[str, Any] = {
        "format": np.array(MAP_FORMAT),
        "version": np.array(MAP_VERSION, dtype=np.int64),
        **{key: np.array(getattr(params, key), dtype=np.float64) for key in _PARAM_KEYS},
        "block_size_cells": np.array(params.block_size_cells, dtype=np.int64),
        "origin_m": np.array(params.origin_m, dtype=np.float64),
        "block_coords": coords.astype(np.int64),
        "known": known,
        "logodds": values.astype(_LOGODDS_TYPES[MAP_VERSION]),  # as stored: float32
    }
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        np.savez_compressed(handle, **arrays)
    return path


def _scalar(path: Path, data: dict[str, np.ndarray], key: str, kind: str) -> Any:
    value = data[key]
    if value.shape != () or value.dtype.kind not in kind:
        raise MapError(f"{path}: {key!r} must be a scalar of kind {kind!r}, got {value.dtype}")
    return value.item()


def load_map(path: Path | str) -> OccupancyGrid:
    """Read a map written by ``save_map``; MapError on anything unexpected.

    Memory is bounded before it is spent: every array's size is checked from the zip directory
    before it is decompressed, and the dense blocks are allocated only when they hold at most
    ``MAX_DENSE_CELLS`` cells and the known cells fill at least 1/``MAX_SPARSITY`` of them (or
    the whole map is small). Maps that coopmap writes are far denser; a crafted file of many
    nearly empty blocks is refused instead of asking for gigabytes.
    """
    path = Path(path)
    if not path.exists():
        raise MapError(f"{path}: no such map file")
    regular_file(path, MapError)  # a FIFO would block, a device fill memory
    try:
        with np.load(path, allow_pickle=False) as archive:
            return _read(path, archive)
    except MapError:
        raise
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as exc:
        raise MapError(f"{path}: not a readable coopmap map: {exc}") from None


def _member(path: Path, archive: Any, key: str, limit_bytes: int) -> np.ndarray:
    """One array of the archive, after checking its declared (uncompressed) size."""
    size = archive.zip.getinfo(key + ".npy").file_size
    if size > limit_bytes + _NPY_HEADER:
        raise MapError(
            f"{path}: {key} declares {size:,} bytes, more than the {limit_bytes + _NPY_HEADER:,} "
            "its map can hold"
        )
    return np.asarray(archive[key])


def _read(path: Path, archive: Any) -> OccupancyGrid:
    missing = [key for key in _KEYS if key not in archive.files]
    if "format" in missing or "version" in missing:
        raise MapError(f"{path}: not a coopmap map (no format/version entry)")
    small = [k for k in _KEYS if k not in ("block_coords", "known", "logodds")]
    data = {k: _member(path, archive, k, 1024) for k in small if k in archive.files}
    if data["format"].shape != () or str(data["format"]) != MAP_FORMAT:
        raise MapError(f"{path}: not a coopmap map (format {data['format']!r})")
    version = _scalar(path, data, "version", "iu")
    if version not in _LOGODDS_TYPES:
        readable = " and ".join(str(v) for v in _LOGODDS_TYPES)
        raise MapError(
            f"{path}: map format version {version} is not supported (this coopmap reads "
            f"versions {readable})"
        )
    value_type = _LOGODDS_TYPES[version]
    if missing:
        raise MapError(f"{path}: map is missing {', '.join(missing)}")
    origin = data["origin_m"]
    if origin.shape != (3,) or origin.dtype.kind != "f":
        raise MapError(f"{path}: origin_m must be 3 floats, got shape {origin.shape}")
    fields = {key: float(_scalar(path, data, key, "f")) for key in _PARAM_KEYS}
    block_size = int(_scalar(path, data, "block_size_cells", "iu"))
    try:
        params = GridParams(
            **fields,
            block_size_cells=block_size,
            origin_m=(float(origin[0]), float(origin[1]), float(origin[2])),
        )
    except MapError as exc:
        raise MapError(f"{path}: {exc}") from None
    bs = params.block_size_cells
    cells = bs**3
    max_blocks = MAX_DENSE_CELLS // cells
    n_bytes = -(-cells // 8)
    coords = _member(path, archive, "block_coords", 24 * max_blocks)
    if coords.ndim != 2 or coords.shape[1] != 3 or coords.dtype.kind not in "iu":
        raise MapError(f"{path}: block_coords must be (B, 3) integers, got {coords.shape}")
    known_bits = _member(path, archive, "known", n_bytes * len(coords))
    if known_bits.shape != (len(coords), n_bytes) or known_bits.dtype != np.uint8:
        raise MapError(
            f"{path}: known must be ({len(coords)}, {n_bytes}) uint8, got {known_bits.shape} "
            f"{known_bits.dtype}"
        )
    if cells % 8:  # bits beyond the last cell of a block are padding
        known_bits[:, -1] &= np.uint8((1 << (cells % 8)) - 1)
    count = int(_POPCOUNT[known_bits].sum(dtype=np.int64))
    dense = len(coords) * cells
    if dense > MAX_DENSE_CELLS or (dense > SMALL_MAP_CELLS and dense > MAX_SPARSITY * count):
        raise MapError(
            f"{path}: {len(coords):,} blocks of {cells:,} cells hold only {count:,} known cells; "
            f"a map is refused when its blocks exceed {MAX_DENSE_CELLS:,} cells, or "
            f"{SMALL_MAP_CELLS:,} cells at under 1/{MAX_SPARSITY} known"
        )
    values = _member(path, archive, "logodds", value_type.itemsize * count)
    if values.ndim != 1 or values.dtype != value_type or len(values) != count:
        raise MapError(
            f"{path}: logodds must hold one {value_type} per known cell ({count}) in version "
            f"{version}, got {values.shape} {values.dtype}"
        )
    if not np.all(np.isfinite(values)):
        raise MapError(f"{path}: logodds holds non-finite values")
    low, high = params.logodds_min, params.logodds_max
    if len(values) and (values.min() < low - 1e-9 or values.max() > high + 1e-9):
        raise MapError(
            f"{path}: logodds outside the clamping bounds [{low:.6g}, {high:.6g}]: "
            f"[{values.min():.6g}, {values.max():.6g}]"
        )
    known = np.unpackbits(known_bits, axis=1, bitorder="little")[:, :cells].astype(bool)
    blocks = np.full(known.shape, np.nan)
    blocks[known] = values
    try:
        return OccupancyGrid.from_blocks(params, coords, blocks.reshape(len(coords), bs, bs, bs))
    except MapError as exc:
        raise MapError(f"{path}: {exc}") from None
