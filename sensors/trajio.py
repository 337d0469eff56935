"""Trajectory and pose-graph files: TUM, g2o (2D), CARMEN logs and SLAM-benchmark relations.

Planar poses are (N, 3) arrays ``x_m, y_m, yaw_rad``. Readers check every line and raise
``TrajectoryError`` naming the file, the line number and what is wrong; writers go through
atomic writes, so a crash never leaves half a file. Nothing here imports gtsam.
"""

from __future__ import annotations

import gzip
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sensors.atomic import write_text_atomic
from sensors.errors import TrajectoryError
from sensors.geometry.se2 import wrap_angle
from sensors.yamlio import regular_file

__all__ = [
    "G2oGraph",
    "as_logged",
    "pose_at",
    "read_carmen_odometry",
    "read_g2o",
    "read_relations",
    "read_tum",
    "tum_rows",
    "tum_text",
    "write_g2o",
    "write_tum",
]


#: The longest line a trajectory file may hold: a g2o edge with its information matrix is about
#: 200 characters; a file of one endless line is not read into memory.
MAX_LINE_CHARS = 1 << 16
#: A TUM file up to this size is read whole and parsed by numpy: a tenth of the time, and about
#: 4 bytes of memory per byte of the file while parsing (the line-by-line reader's lists of
#: fields take 9); a larger one is read line by line.
_AT_ONCE_BYTES = 1 << 26


def _lines(path: Path) -> Iterator[tuple[int, list[str]]]:
    """(line number, fields) of the non-blank, non-comment lines of a text or .gz file.

    A FIFO, a device or a directory is refused before it is opened, and a line longer than
    ``MAX_LINE_CHARS`` is an error, so reading never blocks and never fills memory.
    """
    if path.exists():  # a missing file stays the OSError that open() raises
        regular_file(path, TrajectoryError)
    opener = gzip.open if path.suffix == ".gz" else open
    try:
        with opener(path, "rt", encoding="utf-8") as handle:
            number = 0
            while line := handle.readline(MAX_LINE_CHARS + 1):
                number += 1
                if len(line) > MAX_LINE_CHARS:
                    raise TrajectoryError(
                        f"{path}:{number}: a line longer than {MAX_LINE_CHARS:,} characters"
                    )
                fields = line.split()
                if fields and not fields[0].startswith("#"):
                    yield number, fields
    except (UnicodeDecodeError, gzip.BadGzipFile, EOFError) as exc:
        raise TrajectoryError(f"{path}: not a readable text file ({exc})") from exc


def _floats(path: Path, number: int, fields: list[str], what: str) -> list[float]:
    try:
        values = [float(f) for f in fields]
    except ValueError as exc:
        raise TrajectoryError(f"{path}:{number}: {what}: not a number ({exc})") from exc
    if not all(math.isfinite(v) for v in values):
        raise TrajectoryError(f"{path}:{number}: {what}: non-finite value in {fields}")
    return values


def write_tum(
    path: Path | str,
    stamps_s: np.ndarray,
    poses: np.ndarray,
    *,
    z_m: float = 0.0,
    decimals: int = 9,
) -> Path:
    """Write ``t x y z qx qy qz qw`` lines: planar poses (N, 3) at height ``z_m``, rotated about z
    by their yaw. Stamps and positions carry ``decimals`` digits (9: nanometres; the simulator's
    odometry logs keep 6, micrometres, like a wheel-encoder log); quaternions always 9.
    """
    path = Path(path)
    stamps_s = np.asarray(stamps_s, dtype=float)
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 2 or poses.shape[1] != 3 or stamps_s.shape != (len(poses),):
        raise TrajectoryError(
            f"write_tum: need stamps (N,) and poses (N, 3), got {stamps_s.shape} and {poses.shape}"
        )
    write_text_atomic(path, tum_text(stamps_s, poses, z_m=z_m, decimals=decimals))
    return path


def tum_text(
    stamps_s: np.ndarray, poses: np.ndarray, *, z_m: float = 0.0, decimals: int = 9
) -> str:
    """The text :func:`write_tum` writes."""
    rows = tum_rows(stamps_s, poses, z_m=z_m, decimals=decimals)
    return "# timestamp tx ty tz qx qy qz qw\n" + "".join(r + "\n" for r in rows)


def tum_rows(
    stamps_s: np.ndarray, poses: np.ndarray, *, z_m: float = 0.0, decimals: int = 9
) -> list[str]:
    """The lines :func:`write_tum` writes (without their newlines)."""
    half = np.asarray(poses, dtype=float)[:, 2] / 2.0
    d = decimals
    z = f"{z_m:.{d}f}" if z_m != 0.0 or d != 9 else "0"
    return [
        f"{t:.{d}f} {x:.{d}f} {y:.{d}f} {z} 0 0 {qz:.9f} {qw:.9f}"
        for t, x, y, qz, qw in zip(
            stamps_s, poses[:, 0], poses[:, 1], np.sin(half), np.cos(half), strict=True
        )
    ]


def as_logged(
    stamps_s: np.ndarray, poses: np.ndarray, decimals: int = 9
) -> tuple[np.ndarray, np.ndarray]:
    """Stamps and poses exactly as :func:`read_tum` reads them back from :func:`write_tum`
    with ``decimals`` (what a consumer of a live log sees and what a later reader of the file
    sees are then the same numbers)."""
    rows = tum_rows(np.asarray(stamps_s, dtype=float), np.asarray(poses, dtype=float),
                    decimals=decimals)  # fmt: skip
    values = np.array([row.split() for row in rows], dtype=np.float64).reshape(-1, 8)
    return values[:, 0].copy(), _planar(values)


def pose_at(
    stamps_s: np.ndarray, poses: np.ndarray, t_s: float | np.ndarray, yaw: np.ndarray | None = None
) -> np.ndarray:
    """The planar pose at ``t_s`` of a trajectory (stamps (N,), poses (N, 3)), linear between
    samples (yaw unwrapped), held beyond its ends: (3,), or (M, 3) for M instants. ``yaw``: the
    trajectory's yaw unwrapped (``np.unwrap(poses[:, 2])``), for a caller that asks often (the
    unwrapping takes as long as the trajectory)."""
    yaw = np.unwrap(poses[:, 2]) if yaw is None else yaw
    at = [np.interp(t_s, stamps_s, poses[:, 0]), np.interp(t_s, stamps_s, poses[:, 1]),
          np.interp(t_s, stamps_s, yaw)]  # fmt: skip
    return np.array(at) if np.ndim(t_s) == 0 else np.stack(at, axis=-1)


def read_tum(path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_s (N,), poses (N, 3)) from a TUM file; yaw from the quaternion.

    Rejects lines without 8 numbers, non-unit quaternions, tilted poses (this is a planar
    framework) and timestamps that go backwards, naming the first such line.
    """
    path = Path(path)
    values = _table_at_once(path, 8)
    if values is not None:
        try:
            return _tum_poses(path, values, [], [])
        except TrajectoryError:
            pass  # read again line by line, which names the line
    numbers: list[int] = []
    rows: list[list[str]] = []
    for number, fields in _lines(path):
        if len(fields) != 8:
            raise TrajectoryError(
                f"{path}:{number}: TUM line needs 8 fields (t x y z qx qy qz qw), got {len(fields)}"
            )
        numbers.append(number)
        rows.append(fields)
    if not rows:
        raise TrajectoryError(f"{path}: no poses in the TUM file")
    try:
        values = np.array(rows, dtype=np.float64)
    except ValueError:  # the line-by-line parse names the bad line
        values = np.array(
            [_floats(path, n, fields, "TUM line") for n, fields in zip(numbers, rows, strict=True)]
        )
    return _tum_poses(path, values, numbers, rows)


def _table_at_once(path: Path, width: int) -> np.ndarray | None:
    """The rows (N, ``width``) of an uncompressed regular file of at most ``_AT_ONCE_BYTES``
    whose every non-blank, non-comment line holds ``width`` numbers, read and parsed at once
    (a tenth of the time of the line-by-line reader on a 30,000-line odometry log); None for
    any other file, which the line-by-line reader then reads and names what is wrong in."""
    if path.suffix == ".gz":
        return None
    try:
        if not path.is_file() or path.stat().st_size > _AT_ONCE_BYTES:
            return None
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    # The lines _lines() reads (universal newlines) and keeps (fields, not a comment).
    lines = [row for row in text.split("\n") if row.strip() and not row.lstrip().startswith("#")]
    if not lines or max(map(len, lines)) >= MAX_LINE_CHARS:
        return None
    try:
        values = np.loadtxt(lines, dtype=np.float64, ndmin=2, comments=None)
    except ValueError:
        return None
    return values if values.shape == (len(lines), width) else None


def _tum_poses(
    path: Path, values: np.ndarray, numbers: list[int], rows: list[list[str]]
) -> tuple[np.ndarray, np.ndarray]:
    """Stamps and poses of TUM rows (N, 8) read from lines ``numbers`` (their fields ``rows``),
    checked; the errors name the first bad line (or its row when ``numbers`` is empty)."""
    t, qx, qy, qz, qw = values[:, 0], values[:, 4], values[:, 5], values[:, 6], values[:, 7]

    def first(bad: Any) -> int | None:
        where = np.flatnonzero(np.asarray(bad))
        return int(where[0]) if len(where) else None

    def line(row: int) -> int:
        return numbers[row] if numbers else row + 1

    if (row := first(~np.isfinite(values).all(axis=1))) is not None:
        shown = rows[row] if rows else values[row].tolist()
        raise TrajectoryError(f"{path}:{line(row)}: TUM line: non-finite value in {shown}")
    norm = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if (row := first(np.abs(norm - 1.0) > 1e-3)) is not None:
        raise TrajectoryError(f"{path}:{line(row)}: quaternion norm is {norm[row]:.6g}, not 1")
    if (row := first(np.hypot(qx, qy) / norm > 1e-3)) is not None:
        raise TrajectoryError(
            f"{path}:{line(row)}: pose is tilted (qx={qx[row]}, qy={qy[row]}); planar poses only"
        )
    if (row := first(np.diff(t) < 0.0)) is not None:
        raise TrajectoryError(
            f"{path}:{line(row + 1)}: timestamp {t[row + 1]} goes back (previous {t[row]})"
        )
    return t.copy(), _planar(values)


def _planar(values: np.ndarray) -> np.ndarray:
    """(N, 3) x, y, yaw of TUM rows (N, 8) (yaw from the quaternion about z)."""
    return np.c_[
        values[:, 1], values[:, 2], wrap_angle(2.0 * np.arctan2(values[:, 6], values[:, 7]))
    ]


@dataclass(frozen=True)
class G2oGraph:
    """A 2D pose graph as in g2o files.

    ``vertex_ids`` (N,) and ``poses`` (N, 3); ``edges`` (M, 2) vertex ids ``i j``;
    ``measurements`` (M, 3): pose of j in i's frame; ``information`` (M, 3, 3);
    ``fixed``: ids of ``FIX`` lines.
    """

    vertex_ids: np.ndarray
    poses: np.ndarray
    edges: np.ndarray
    measurements: np.ndarray
    information: np.ndarray
    fixed: tuple[int, ...] = field(default=())

    @property
    def num_poses(self) -> int:
        if len(self.vertex_ids):
            return len(self.vertex_ids)
        return len(np.unique(self.edges))


_UPPER = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


def read_g2o(path: Path | str) -> G2oGraph:
    """Read ``VERTEX_SE2``, ``EDGE_SE2`` and ``FIX`` lines; anything else is an error."""
    path = Path(path)
    vertex_ids: list[int] = []
    poses: list[list[float]] = []
    edges: list[tuple[int, int]] = []
    measurements: list[list[float]] = []
    information: list[np.ndarray] = []
    fixed: list[int] = []
    seen: set[int] = set()
    for number, fields in _lines(path):
        tag = fields[0]
        if tag == "VERTEX_SE2":
            if len(fields) != 5:
                raise TrajectoryError(
                    f"{path}:{number}: VERTEX_SE2 needs 'id x y theta', got {len(fields) - 1} "
                    "values"
                )
            vid = _int(path, number, fields[1])
            if vid in seen:
                raise TrajectoryError(f"{path}:{number}: vertex {vid} defined twice")
            seen.add(vid)
            vertex_ids.append(vid)
            poses.append(_floats(path, number, fields[2:], "VERTEX_SE2"))
        elif tag == "EDGE_SE2":
            if len(fields) != 12:
                raise TrajectoryError(
                    f"{path}:{number}: EDGE_SE2 needs 'i j dx dy dtheta' and 6 information "
                    f"values, got {len(fields) - 1} values"
                )
            i, j = _int(path, number, fields[1]), _int(path, number, fields[2])
            values = _floats(path, number, fields[3:], "EDGE_SE2")
            info = np.zeros((3, 3))
            for (r, c), v in zip(_UPPER, values[3:], strict=True):
                info[r, c] = info[c, r] = v
            if np.linalg.eigvalsh(info).min() <= 0:
                raise TrajectoryError(
                    f"{path}:{number}: EDGE_SE2 {i}-{j}: information matrix is not positive "
                    "definite"
                )
            edges.append((i, j))
            measurements.append(values[:3])
            information.append(info)
        elif tag == "FIX":
            fixed += [_int(path, number, f) for f in fields[1:]]
        else:
            raise TrajectoryError(f"{path}:{number}: unsupported g2o record {tag!r}")
    if not vertex_ids and not edges:
        raise TrajectoryError(f"{path}: no VERTEX_SE2 or EDGE_SE2 lines")
    missing = {v for e in edges for v in e} - seen if vertex_ids else set()
    if missing:
        raise TrajectoryError(
            f"{path}: edges refer to undefined vertices {sorted(missing)[:5]}"
            + (" …" if len(missing) > 5 else "")
        )
    return G2oGraph(
        vertex_ids=np.asarray(vertex_ids, dtype=np.int64),
        poses=np.asarray(poses, dtype=float).reshape(-1, 3),
        edges=np.asarray(edges, dtype=np.int64).reshape(-1, 2),
        measurements=np.asarray(measurements, dtype=float).reshape(-1, 3),
        information=np.asarray(information, dtype=float).reshape(-1, 3, 3),
        fixed=tuple(fixed),
    )


def _int(path: Path, number: int, text: str) -> int:
    try:
        value = int(text)
    except ValueError as exc:
        raise TrajectoryError(f"{path}:{number}: vertex id {text!r} is not an integer") from exc
    if value < 0:
        raise TrajectoryError(f"{path}:{number}: vertex id {value} is negative")
    return value


def write_g2o(path: Path | str, graph: G2oGraph) -> Path:
    """Write a 2D pose graph in g2o format (readable by g2o, GTSAM's readG2o, :func:`read_g2o`)."""
    path = Path(path)
    out = [
        f"VERTEX_SE2 {vid} {x:.9g} {y:.9g} {t:.9g}\n"
        for vid, (x, y, t) in zip(graph.vertex_ids, graph.poses, strict=True)
    ]
    for (i, j), (dx, dy, dt), info in zip(
        graph.edges, graph.measurements, graph.information, strict=True
    ):
        upper = " ".join(f"{info[r, c]:.9g}" for r, c in _UPPER)
        out.append(f"EDGE_SE2 {i} {j} {dx:.9g} {dy:.9g} {dt:.9g} {upper}\n")
    if graph.fixed:
        out.append("FIX " + " ".join(str(v) for v in graph.fixed) + "\n")
    write_text_atomic(path, "".join(out))
    return path


def read_carmen_odometry(path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_s (N,), poses (N, 3)) from the ``ODOM`` lines of a CARMEN log (.gz or text).

    Fields: ``ODOM x y theta tv rv accel ipc_time host logger_time``; the stamp is ``ipc_time``.
    Lines stamped 0 are skipped: the corrected logs insert them after each scan to reset the
    pose, and they carry no time.
    """
    path = Path(path)
    stamps: list[float] = []
    poses: list[list[float]] = []
    for number, fields in _lines(path):
        if fields[0] != "ODOM":
            continue
        if len(fields) < 8:
            raise TrajectoryError(
                f"{path}:{number}: ODOM line needs x y theta tv rv accel ipc_time, got "
                f"{len(fields) - 1} fields"
            )
        x, y, theta, *_, stamp = _floats(path, number, fields[1:8], "ODOM line")
        if stamp > 0:
            stamps.append(stamp)
            poses.append([x, y, theta])
    if not stamps:
        raise TrajectoryError(f"{path}: no timestamped ODOM lines")
    return np.asarray(stamps), np.asarray(poses)


def read_relations(path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (M, 2) ``t1 t2``, relations (M, 3) ``x y yaw``) of a SLAM-benchmark file.

    Lines ``t1 t2 x y z roll pitch yaw`` (Kümmerle et al. 2009): the motion from the pose at t1 to
    the pose at t2 in the t1 frame; z, roll and pitch are ignored (planar data).
    """
    path = Path(path)
    stamps: list[list[float]] = []
    relations: list[list[float]] = []
    for number, fields in _lines(path):
        if len(fields) != 8:
            raise TrajectoryError(
                f"{path}:{number}: relation needs 8 fields (t1 t2 x y z roll pitch yaw), got "
                f"{len(fields)}"
            )
        t1, t2, x, y, _, _, _, yaw = _floats(path, number, fields, "relation")
        stamps.append([t1, t2])
        relations.append([x, y, yaw])
    if not stamps:
        raise TrajectoryError(f"{path}: no relations")
    return np.asarray(stamps), np.asarray(relations)
