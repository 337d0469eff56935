"""PLY point clouds (binary little-endian), readable by Open3D, CloudCompare, MeshLab and PCL.

Besides x, y, z a cloud may carry 8-bit colours (red, green, blue) and any number of named
scalar properties (e.g. ``probability`` of an occupied voxel, ``range_m`` of a laser return).
``write_grid_ply`` exports an occupancy grid's occupied voxel centres that way.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mapping.errors import MapError
from mapping.grid import OccupancyGrid
from sensors.atomic import atomic_path

__all__ = ["PlyError", "read_ply", "write_grid_ply", "write_ply"]

_PLY_TYPES: dict[np.dtype, str] = {
    np.dtype("float32"): "float",
    np.dtype("float64"): "double",
    np.dtype("int32"): "int",
    np.dtype("uint8"): "uchar",
    np.dtype("int16"): "short",
    np.dtype("uint16"): "ushort",
    np.dtype("uint32"): "uint",
    np.dtype("int8"): "char",
}
_NUMPY_TYPES: dict[str, np.dtype] = {name: dtype for dtype, name in _PLY_TYPES.items()} | {
    "float32": np.dtype("float32"),
    "float64": np.dtype("float64"),
    "int8": np.dtype("int8"),
    "uint8": np.dtype("uint8"),
    "int16": np.dtype("int16"),
    "uint16": np.dtype("uint16"),
    "int32": np.dtype("int32"),
    "uint32": np.dtype("uint32"),
}


class PlyError(MapError):
    """A PLY file is malformed, truncated or of an unsupported kind."""


def write_ply(
    path: Path | str,
    points: np.ndarray,
    *,
    colors: np.ndarray | None = None,
    fields: dict[str, np.ndarray] | None = None,
) -> None:
    """Write (N, 3) ``points`` with optional (N, 3) uint8 ``colors`` and scalar ``fields``."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise PlyError(f"points must be (N, 3), got {points.shape}")
    n = len(points)
    columns: list[tuple[str, np.ndarray]] = [
        (axis, points[:, k].astype(np.float32)) for k, axis in enumerate("xyz")
    ]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != (n, 3):
            raise PlyError(f"colors must be ({n}, 3), got {colors.shape}")
        columns += [
            (c, colors[:, k].astype(np.uint8)) for k, c in enumerate(("red", "green", "blue"))
        ]
    for name, values in (fields or {}).items():
        values = np.asarray(values)
        if values.shape != (n,):
            raise PlyError(f"field {name!r} must be ({n},), got {values.shape}")
        if values.dtype not in _PLY_TYPES:
            values = values.astype(np.float64 if values.dtype.kind == "f" else np.int32)
        columns.append((name, values))
    record = np.empty(n, dtype=[(name, values.dtype.newbyteorder("<")) for name, values in columns])
    for name, values in columns:
        record[name] = values
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment written by coopmap",
        f"element vertex {n}",
    ]
    header += [
        f"property {_PLY_TYPES[values.dtype.newbyteorder('=')]} {name}" for name, values in columns
    ]
    header.append("end_header")
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        handle.write(record.tobytes())


def read_ply(path: Path | str) -> dict[str, np.ndarray]:
    """Read the vertex element of a binary little-endian PLY into named columns."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise PlyError(f"{path}: cannot read: {exc.strerror or exc}") from None
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise PlyError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise PlyError(f"{path}: only binary_little_endian PLY is supported")
    count, dtype_fields, in_vertex = None, [], False
    for line in lines:
        words = line.split()
        if words[:2] == ["element", "vertex"] and len(words) == 3:
            count, in_vertex = int(words[2]), True
        elif words[:1] == ["element"]:
            in_vertex = False
        elif in_vertex and words[:1] == ["property"]:
            if len(words) != 3 or words[1] not in _NUMPY_TYPES:
                raise PlyError(f"{path}: unsupported vertex property {line!r}")
            dtype_fields.append((words[2], _NUMPY_TYPES[words[1]].newbyteorder("<")))
    if count is None:
        raise PlyError(f"{path}: no vertex element")
    dtype = np.dtype(dtype_fields)
    body = data[end + len(b"end_header\n") :]
    if len(body) < count * dtype.itemsize:
        raise PlyError(
            f"{path}: truncated: {count} vertices need {count * dtype.itemsize} bytes, "
            f"found {len(body)}"
        )
    record = np.frombuffer(body, dtype=dtype, count=count)
    return {
        name: record[name].astype(record[name].dtype.newbyteorder("="))
        for name in dtype.names or ()
    }


def write_grid_ply(path: Path | str, grid: OccupancyGrid, threshold: float | None = None) -> int:
    """Write the centres of the grid's occupied cells (P > ``threshold``, default the grid's)
    with their ``probability`` (float32) as a PLY; return how many were written."""
    cells, probability = grid.occupied(threshold)
    write_ply(
        path, grid.cell_centers(cells), fields={"probability": probability.astype(np.float32)}
    )
    return len(cells)
