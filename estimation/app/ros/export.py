"""``coopmap export RESULT --mcap OUT.mcap``: a result folder as a ROS 2 bag (docs/ros.md).

Topics (frames ``map``, ``<robot>/odom``, ``<robot>/base_link``, ``<robot>/scanner``,
``<robot>/beacon``; stamps are mission time):

* ``/map`` ``nav_msgs/OccupancyGrid`` — the ceiling band (0–100, unknown −1), at the end;
* ``/map/points`` ``sensor_msgs/PointCloud2`` — occupied voxel centres with their probability;
* ``/map/voxels`` ``foxglove_msgs/VoxelGrid`` — the box around the occupied voxels, every cell
  with its probability (NaN unknown) and a colour (by height; transparent unless occupied);
* ``/octomap_binary`` ``octomap_msgs/Octomap`` — the binary tree of ``map.bt``;
* ``/<robot>/path`` ``nav_msgs/Path`` — the poses so far, at each pose's stamp;
* ``/<robot>/pose`` ``geometry_msgs/PoseWithCovarianceStamped`` — each pose and its marginal;
* ``/tf`` — ``map`` → ``<robot>/odom`` at each pose's stamp, ``<robot>/odom`` →
  ``<robot>/base_link`` at every odometry sample of the dataset (or at the poses' stamps, with
  ``map`` = ``odom``, when the dataset is not at hand);
* ``/tf_static`` — scanner and beacon mounts;
* ``/markers`` ``visualization_msgs/MarkerArray`` — mutual observations and search results.

The live view (:mod:`estimation.app.ros.live_view`) publishes the same messages, built by
:func:`result_messages`, over a Foxglove WebSocket.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimation.app.config import Config, load_config
from estimation.app.rig import T_robot_scanner, cut_ceiling_band
from estimation.app.ros.bag import BagMessage, check_mcap_replaceable, write_mcap
from estimation.app.ros.messages import Color, RosMessages, covariance_6x6, stamp_ns
from estimation.errors import EstimationError
from mapping.errors import MapError
from mapping.formats.npz import load_map
from mapping.formats.octomap_bt import encode_bt, tree_stream
from mapping.grid import OccupancyGrid
from mapping.logodds import probability
from sensors.geometry import se2
from sensors.trajio import pose_at, read_tum
from sensors.yamlio import read_text_file

__all__ = [
    "VOXEL_DTYPE",
    "ExportSummary",
    "ResultContent",
    "Trajectory",
    "export_result",
    "read_result",
    "read_trajectories",
    "result_messages",
    "static_tf",
    "voxel_block",
]

#: report.json and covariances.json of a very long mission stay far below this.
_JSON_LIMIT_BYTES = 512 * 2**20
_MUTUAL_COLORS = {
    "inlier": Color(0.1, 0.75, 0.2),
    "outlier": Color(1.0, 0.55, 0.0),
    "rejected": Color(0.9, 0.1, 0.1),
}
_POSE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
#: One cell of ``/map/voxels``: its probability of occupancy (NaN unknown) and its colour.
VOXEL_DTYPE = np.dtype(
    [("probability", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")]
)
#: Height colours of occupied voxels, bottom to top of the box (blue, cyan, green, yellow, red).
_HEIGHT_COLORS = np.array(
    [[48, 18, 160], [30, 160, 230], [60, 200, 80], [240, 200, 30], [200, 30, 20]], dtype=float
)
_SEARCH_COLORS = {
    "used": Color(0.15, 0.4, 1.0),
    "unused": Color(0.6, 0.6, 0.6),
    "relocalize": Color(0.7, 0.2, 0.9),
}


@dataclass(frozen=True)
class Trajectory:
    """One robot's poses in a result: pose indices, stamps (s), poses (N, 3) in the map frame
    and their marginal covariances (N, 3, 3) in the poses' tangent spaces, or None."""

    indices: list[int]
    stamps_s: np.ndarray
    poses: np.ndarray
    covariances: np.ndarray | None


@dataclass(frozen=True)
class ResultContent:
    """A result folder as its ROS topics need it: the effective config, ``report.json``, the
    robots' poses, the dataset's odometry (None when not at hand), the 3D map and what had to
    be left out."""

    config: Config
    report: dict[str, Any]
    trajectories: dict[str, Trajectory]
    odometry: dict[str, tuple[np.ndarray, np.ndarray]] | None
    grid: OccupancyGrid
    notes: list[str]


@dataclass(frozen=True)
class ExportSummary:
    """What an export wrote: the file, messages per topic, and what it had to leave out."""

    path: Path
    topics: dict[str, int]
    notes: list[str] = field(default_factory=list)


def _read_json(path: Path) -> dict[str, Any]:
    try:
        document = json.loads(read_text_file(path, EstimationError, _JSON_LIMIT_BYTES))
    except json.JSONDecodeError as exc:
        raise EstimationError(f"{path}: not JSON ({exc.msg})") from None
    if not isinstance(document, dict):
        raise EstimationError(f"{path}: not a JSON object")
    return document


def read_trajectories(result: Path, report: dict[str, Any]) -> dict[str, Trajectory]:
    """Every robot's poses of a result folder (``poses/``, ``covariances.json``)."""
    cov_path = result / "covariances.json"
    cov_doc = _read_json(cov_path).get("robots", {}) if cov_path.is_file() else {}
    labels = report.get("g2o_vertices", {})
    out = {}
    for robot in report.get("robots", {}):
        tum = result / "poses" / f"{robot}.tum"
        if not tum.is_file():
            continue
        stamps, poses = read_tum(tum)
        entry = cov_doc.get(robot)
        if entry is not None:
            indices = [int(i) for i in entry["indices"]]
            covariances: np.ndarray | None = np.asarray(entry["covariances"], dtype=float)
        else:
            indices = sorted(int(k[1:]) for k in labels if k[:1] == robot and k[1:].isdigit())
            covariances = None
        if len(indices) != len(stamps) or (
            covariances is not None and covariances.shape != (len(stamps), 3, 3)
        ):
            raise EstimationError(
                f"{tum}: {len(stamps)} poses, but the result lists {len(indices)} pose indices "
                f"of robot {robot!r}"
            )
        out[robot] = Trajectory(indices, stamps, poses, covariances)
    return out


def _odometry(
    candidates: list[Path], robots: list[str], required: bool
) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
    for folder in candidates:
        files = [folder / "robots" / r / "odometry.tum" for r in robots]
        if all(f.is_file() for f in files):
            return {r: read_tum(f) for r, f in zip(robots, files, strict=True)}
    if required:
        raise EstimationError(f"{candidates[0]}: no robots/<robot>/odometry.tum for {robots}")
    return None


def _frames(robot: str) -> tuple[str, str]:
    return f"{robot}/odom", f"{robot}/base_link"


def static_tf(ros: RosMessages, config: Config, robots: list[str]) -> BagMessage:
    """The mounts on every robot: scanner (``T_robot_scanner``) and beacon (``beacon.offset_m``
    ahead of the scanner, centre ``beacon.height_m`` above the floor); axes as the robot's."""
    mount = T_robot_scanner(config)
    scanner = (float(mount[0, 3]), float(mount[1, 3]), 0.0)
    beacon = (config.robot.scanner_x_m + config.beacon.offset_m, 0.0, 0.0)
    transforms = []
    for robot in robots:
        base = _frames(robot)[1]
        transforms += [
            ros.transform(0, base, f"{robot}/scanner", scanner, float(mount[2, 3])),
            ros.transform(0, base, f"{robot}/beacon", beacon, config.beacon.height_m),
        ]
    return BagMessage("/tf_static", "tf2_msgs/msg/TFMessage", 0, ros.tf(transforms), True)


def _robot_messages(
    ros: RosMessages,
    robot: str,
    trajectory: Trajectory,
    odometry: tuple[np.ndarray, np.ndarray] | None,
) -> list[BagMessage]:
    """A robot's frames, path and poses. ``map`` → ``odom`` at each pose's stamp is the pose
    composed with the inverse of the odometry there; ``odom`` → ``base_link`` is the odometry."""
    odom, base = _frames(robot)
    out: list[BagMessage] = []

    def tf(ns: int, parent: str, child: str, pose: np.ndarray) -> BagMessage:
        message = ros.tf([ros.transform(ns, parent, child, pose)])
        return BagMessage("/tf", "tf2_msgs/msg/TFMessage", ns, message)

    stamped = []
    stamps = np.asarray(trajectory.stamps_s, dtype=float)
    odom_poses = None if odometry is None else pose_at(*odometry, stamps).reshape(-1, 3)
    for n, (t_s, pose) in enumerate(zip(stamps, trajectory.poses, strict=True)):
        ns = stamp_ns(float(t_s))
        if odom_poses is None:
            out += [tf(ns, "map", odom, np.zeros(3)), tf(ns, odom, base, pose)]
        else:
            out.append(tf(ns, "map", odom, se2.compose(pose, se2.inverse(odom_poses[n]))))
        stamped.append(ros.pose_stamped(ns, "map", pose))
        path = ros.path(ns, "map", list(stamped))
        out.append(BagMessage(f"/{robot}/path", "nav_msgs/msg/Path", ns, path))
        covariance = (
            np.zeros((6, 6))
            if trajectory.covariances is None
            else covariance_6x6(trajectory.covariances[n], float(pose[2]))
        )
        message = ros.pose_with_covariance(ns, "map", pose, covariance)
        out.append(BagMessage(f"/{robot}/pose", _POSE_TYPE, ns, message))
    if odometry is not None:
        out += [tf(stamp_ns(float(t)), odom, base, p) for t, p in zip(*odometry, strict=True)]
    return out


def _markers(
    ros: RosMessages,
    ns: int,
    report: dict[str, Any],
    trajectories: dict[str, Trajectory],
    beacon_height_m: float,
) -> list[Any]:
    """Mutual observations as arrows from observer to observed (at the beacons' height), and
    each search result as an arrow at the pose the search found, in the map frame."""
    poses = {
        f"{r}{i}": p
        for r, t in trajectories.items()
        for i, p in zip(t.indices, t.poses, strict=True)
    }
    markers: list[Any] = []
    for row in report.get("mutual_observations", []):
        a, c = row["pair"]
        if a not in poses or c not in poses:
            continue
        state = "rejected" if not row["accepted"] else "inlier" if row.get("inlier") else "outlier"
        ends = np.array([[*poses[a][:2], beacon_height_m], [*poses[c][:2], beacon_height_m]])
        markers.append(
            ros.marker(
                ns,
                "map",
                "mutual",
                len(markers),
                kind="ARROW",
                color=_MUTUAL_COLORS[state],
                scale=(0.03, 0.08, 0.12),
                points=ends,
                text=f"{a}-{c}",
            )
        )
    found = report.get("global_localization", {})
    searches = 0
    for record in [*found.get("searches", []), *found.get("relocalization", [])]:
        anchor = record["against"]
        if anchor != "map" and anchor not in poses:
            continue
        pose = record["pose"] if anchor == "map" else se2.compose(poses[anchor], record["pose"])
        kind = (
            "relocalize"
            if record.get("kind") == "relocalize"
            else ("used" if record.get("used") else "unused")
        )
        markers.append(
            ros.marker(
                ns,
                "map",
                "search",
                searches,
                kind="ARROW",
                color=_SEARCH_COLORS[kind],
                scale=(0.6, 0.1, 0.1),
                pose=pose,
                z_m=0.05,
                text=f"{record['station']} vs {anchor}",
            )
        )
        searches += 1
    return markers


def voxel_block(grid: OccupancyGrid) -> tuple[np.ndarray, np.ndarray] | None:
    """The box of cells around the occupied voxels (P > ``occupied_threshold``): its lowest cell
    index (3,) and a (nz, ny, nx) array of ``VOXEL_DTYPE`` indexed [k, j, i] by the cell's
    offset from it. Known cells carry their probability, unknown cells NaN; occupied cells are
    opaque and coloured by height, the others transparent. None when no voxel is occupied."""
    cells, values = grid.cells()
    occupied = values > grid.params.logodds_threshold
    if not occupied.any():
        return None
    lower, upper = cells[occupied].min(axis=0), cells[occupied].max(axis=0)
    nx, ny, nz = (upper - lower + 1).tolist()
    block = np.zeros((nz, ny, nx), dtype=VOXEL_DTYPE)
    block["probability"] = np.nan
    inside = np.all((cells >= lower) & (cells <= upper), axis=1)
    i, j, k = (cells[inside] - lower).T
    block["probability"][k, j, i] = probability(values[inside])
    i, j, k = (cells[occupied] - lower).T
    height = k / max(nz - 1, 1) * (len(_HEIGHT_COLORS) - 1)
    stops = np.arange(len(_HEIGHT_COLORS))
    for c, name in enumerate(("red", "green", "blue")):
        block[name][k, j, i] = np.rint(np.interp(height, stops, _HEIGHT_COLORS[:, c]))
    block["alpha"][k, j, i] = 255
    return lower, block


def _map_messages(
    ros: RosMessages, ns: int, grid: OccupancyGrid, config: Config
) -> tuple[list[BagMessage], list[str]]:
    """The ceiling band, the occupied voxels (as points and as a voxel grid) and the OctoMap
    tree of ``grid``; and notes on what could not be written."""
    out, notes = [], []
    try:
        ceiling = cut_ceiling_band(grid, config)
        out.append(
            BagMessage(
                "/map",
                "nav_msgs/msg/OccupancyGrid",
                ns,
                ros.occupancy_grid(ns, "map", ceiling),
                True,
            )
        )
    except MapError as exc:
        notes.append(f"/map not written: {exc}")
    cells, p_occupied = grid.occupied()
    cloud = ros.point_cloud(ns, "map", grid.cell_centers(cells), p_occupied)
    out.append(BagMessage("/map/points", "sensor_msgs/msg/PointCloud2", ns, cloud, True))
    block = voxel_block(grid)
    if block is None:
        notes.append("/map/voxels not written: no voxel is occupied")
    else:
        lower_m = grid.origin_m + block[0] * grid.resolution_m
        voxels = ros.voxel_grid(ns, "map", lower_m, grid.resolution_m, block[1])
        out.append(BagMessage("/map/voxels", "foxglove_msgs/msg/VoxelGrid", ns, voxels, True))
    if any(v != 0.0 for v in grid.params.origin_m):
        notes.append("/octomap_binary not written: the grid's lattice is not OctoMap's")
        return out, notes
    known, values = grid.cells()
    data = encode_bt(known, values > grid.params.logodds_threshold, grid.resolution_m)
    tree_id, resolution_m, stream = tree_stream(data)
    out.append(
        BagMessage(
            "/octomap_binary",
            "octomap_msgs/msg/Octomap",
            ns,
            ros.octomap(ns, "map", tree_id, resolution_m, stream),
            True,
        )
    )
    return out, notes


def read_result(result_dir: Path | str, *, dataset_dir: Path | str | None = None) -> ResultContent:
    """A result folder's config, report, poses and map, and the dataset's odometry.

    The odometry comes from the dataset's ``robots/<robot>/odometry.tum``: ``dataset_dir`` if
    given (then it must be there), else the dataset ``report.json`` names, else the result's
    parent folder.
    """
    result = Path(result_dir)
    report_path = result / "report.json"
    if not report_path.is_file():
        raise EstimationError(f"{result}: no result here (report.json missing): run coopmap batch")
    report = _read_json(report_path)
    config = load_config(result / "config.yaml")
    trajectories = read_trajectories(result, report)
    if not trajectories:
        raise EstimationError(f"{result}: no robot has poses (poses/<robot>.tum)")
    candidates = (
        [Path(dataset_dir)]
        if dataset_dir is not None
        else [Path(str(report.get("dataset", result.parent))), result.parent]
    )
    odometry = _odometry(candidates, list(trajectories), required=dataset_dir is not None)
    notes = []
    if odometry is None:
        notes.append("no dataset odometry found: <robot>/odom is the map frame")
    if any(t.covariances is None for t in trajectories.values()):
        notes.append("the result holds no covariances.json: pose covariances are zero")
    grid = load_map(result / "map.npz")
    return ResultContent(config, report, trajectories, odometry, grid, notes)


def result_messages(
    ros: RosMessages,
    config: Config,
    trajectories: dict[str, Trajectory],
    grid: OccupancyGrid,
    *,
    odometry: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
    report: dict[str, Any] | None = None,
) -> tuple[list[BagMessage], list[str]]:
    """Every topic's messages of a mission's state: frames, paths and poses at their stamps;
    maps and markers (from ``report``'s mutual observations and searches) at its end, the
    latest stamp of the poses and the odometry. Also notes on what could not be written."""
    robots = list(trajectories)
    last = [float(t.stamps_s.max()) for t in trajectories.values() if len(t.stamps_s)]
    last += [float(o[0].max()) for o in (odometry or {}).values() if len(o[0])]
    end_ns = stamp_ns(max(last, default=0.0))
    messages = [static_tf(ros, config, robots)]
    for robot, trajectory in trajectories.items():
        messages += _robot_messages(
            ros, robot, trajectory, None if odometry is None else odometry[robot]
        )
    maps, notes = _map_messages(ros, end_ns, grid, config)
    messages += maps
    markers = _markers(ros, end_ns, report or {}, trajectories, config.beacon.height_m)
    if markers:
        messages.append(
            BagMessage(
                "/markers",
                "visualization_msgs/msg/MarkerArray",
                end_ns,
                ros.marker_array(markers),
                True,
            )
        )
    return messages, notes


def export_result(
    result_dir: Path | str, mcap_path: Path | str, *, dataset_dir: Path | str | None = None
) -> ExportSummary:
    """Write a result folder's maps, poses, frames and markers as an MCAP bag.

    The odometry frames come from the dataset's ``robots/<robot>/odometry.tum``: ``dataset_dir``
    if given, else the dataset ``report.json`` names, else the result's parent folder.
    """
    check_mcap_replaceable(mcap_path)
    content = read_result(result_dir, dataset_dir=dataset_dir)
    ros = RosMessages()
    messages, notes = result_messages(
        ros,
        content.config,
        content.trajectories,
        content.grid,
        odometry=content.odometry,
        report=content.report,
    )
    path = write_mcap(mcap_path, messages, ros)
    topics: dict[str, int] = {}
    for m in messages:
        topics[m.topic] = topics.get(m.topic, 0) + 1
    return ExportSummary(path, topics, content.notes + notes)
