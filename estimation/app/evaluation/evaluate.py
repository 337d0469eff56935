"""``coopmap evaluate``: a result against its dataset's ground truth → ``metrics.json``.

* Trajectories: the pose of every (robot, index) in ``poses/<robot>.tum`` against the true pose
  (``ground_truth/<robot>.tum``) at its stamp, an instant of the standstill at that stop. The
  gauge is the first robot's declared start, so estimate and truth share the map frame: ATE is
  computed without alignment (RMS of position and heading errors); RPE over consecutive poses
  of each robot.
* Mutual localization: every mutual factor's relative pose against the true relative pose; the
  gate's rejections and GNC's outliers are counted.
* Map: occupied cells (P > the grid's threshold) against the voxels the world's surfaces pass
  through (``sensors.sim.truth``), at the map's resolution. Precision: the share of occupied
  cells within one cell of a true surface voxel; recall: the share of true surface voxels the
  map observed (known, occupied or free) that are within one cell of an occupied cell.
* Figure: ``figures/ceiling_truth.png`` in the result, the ceiling band under the true walls
  with the estimated and the true poses.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, StringConstraints

from estimation.app.evaluation.metrics import ate, rpe
from estimation.errors import EstimationError
from mapping.errors import MapError
from mapping.formats.npz import load_map
from sensors.atomic import output_kind, write_text_atomic
from sensors.sim.scene import build_mesh
from sensors.sim.truth import surface_voxels
from sensors.sim.world import load_world
from sensors.trajio import read_tum
from sensors.yamlio import read_text_file, validate_mapping

__all__ = ["evaluate", "map_quality"]


@functools.lru_cache(maxsize=16)
def _truth_track(path: str, stamp: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """A ground-truth file's stamps and (x, y, unwrapped yaw), read once per file version
    (``stamp``: its modification time and size)."""
    t, poses = read_tum(path)
    return t, np.column_stack([poses[:, 0], poses[:, 1], np.unwrap(poses[:, 2])])


def _truth_at(dataset: Path, robot: str, stamps: np.ndarray) -> np.ndarray:
    path = dataset / "ground_truth" / f"{robot}.tum"
    if not path.exists():  # a FIFO or a folder in its place is refused by read_tum
        raise EstimationError(f"{dataset}: no ground truth for robot {robot!r} ({path.name})")
    info = path.stat()
    t, poses = _truth_track(str(path), (info.st_mtime_ns, info.st_size))
    return np.column_stack([np.interp(stamps, t, poses[:, k]) for k in range(3)])


def _keys(cells: np.ndarray) -> np.ndarray:
    """Sorted unique int64 keys of (N, 3) cell indices (21 bits a coordinate, offset)."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3) + (1 << 20)
    return np.unique((c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2])


def _dilate(keys: np.ndarray) -> np.ndarray:
    """The keys of every cell within one cell (26-neighbourhood) of a key of ``keys``."""
    offsets = [(di << 42) + (dj << 21) + dk
               for di in (-1, 0, 1) for dj in (-1, 0, 1) for dk in (-1, 0, 1)]  # fmt: skip
    return np.unique(np.concatenate([keys + o for o in offsets]))


def _within(keys: np.ndarray, sorted_keys: np.ndarray) -> np.ndarray:
    """Which ``keys`` are in ``sorted_keys`` (sorted unique)."""
    if not len(sorted_keys):
        return np.zeros(len(keys), dtype=bool)
    at = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return sorted_keys[at] == keys


def map_quality(grid: Any, world_path: Path) -> dict[str, Any]:
    """Precision and recall of the occupied cells against the world's surface voxels."""
    world = load_world(world_path)
    params = grid.params
    truth = surface_voxels(build_mesh(world), params.resolution_m, np.asarray(params.origin_m))
    true_cells = _keys(truth.indices)
    occupied, _ = grid.occupied()
    occupied_cells = _keys(occupied)
    if not len(occupied_cells):
        return {"resolution_m": params.resolution_m, "precision": 0.0, "recall": 0.0, "occupied": 0}
    precision = float(_within(occupied_cells, _dilate(true_cells)).mean())
    known_cells, _ = grid.cells()
    observed_truth = true_cells[_within(true_cells, _keys(known_cells))]
    near_map = _dilate(occupied_cells)
    recall = float(_within(observed_truth, near_map).sum()) / max(1, len(observed_truth))
    return {
        "resolution_m": params.resolution_m,
        "precision": precision,
        "recall": recall,
        "occupied": len(occupied_cells),
        "true_surface_voxels_observed": len(observed_truth),
        "true_surface_voxels": len(true_cells),
    }


Label = Annotated[str, StringConstraints(pattern=r"^[a-z][0-9]+$")]
Pose = Annotated[list[float], Field(min_length=3, max_length=3)]


class _Loose(BaseModel):
    model_config = ConfigDict(extra="allow")


class _Search(_Loose):
    station: Label
    against: Label | Literal["map"]
    kind: str = "loop"
    band: str = "ceiling"
    pose: Pose
    used: bool = False
    time_s: float = 0.0


class _Localization(_Loose):
    factors: int = 0
    validation: dict[str, Any] | None = None
    searches: list[_Search] = []
    relocalization: list[_Search] = []


class _Observation(_Loose):
    pair: Annotated[list[Label], Field(min_length=2, max_length=2)]
    measurement: Pose | None = None
    accepted: bool


class _Report(_Loose):
    """The parts of ``report.json`` that ``evaluate`` reads (docs/results.md)."""

    robots: dict[Annotated[str, StringConstraints(pattern=r"^[a-z]$")], dict[str, Any]]
    observations: int
    gate_rejections: list[Any]
    outlier_factors: list[Any]
    timings_s: dict[str, float]
    missing_sweeps: list[Any]
    unseen_pairs: list[Any]
    dropped_poses: list[Any]
    mutual_observations: list[_Observation] = []
    global_localization: _Localization = _Localization()


#: report.json of a very long mission stays far below this.
REPORT_LIMIT_BYTES = 512 * 2**20


def read_report(path: Path) -> dict[str, Any]:
    """``report.json`` of a result, checked: malformed, truncated or foreign files are one-line
    errors naming the file and the key."""
    text = read_text_file(path, EstimationError, REPORT_LIMIT_BYTES)
    try:
        document = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        what = exc.msg if isinstance(exc, json.JSONDecodeError) else "nested too deeply"
        raise EstimationError(f"{path}: not a coopmap report (not JSON: {what})") from None
    if not isinstance(document, dict):
        raise EstimationError(f"{path}: not a coopmap report (a {type(document).__name__})")
    validate_mapping(_Report, document, EstimationError, f"{path}: not a coopmap report")
    return document


def evaluate(dataset_dir: Path | str, result_dir: Path | str | None = None) -> dict[str, Any]:
    dataset = Path(dataset_dir)
    result = Path(result_dir) if result_dir is not None else dataset / "result"
    report_path = result / "report.json"
    if result.is_symlink():
        raise EstimationError(f"{result}: is a symbolic link; evaluate writes metrics.json only "
                              "into a result folder itself")  # fmt: skip
    if not report_path.exists():  # a FIFO or a folder in its place is refused when read
        raise EstimationError(f"{result}: no result here (report.json missing): run coopmap batch")
    report = read_report(report_path)
    if output_kind(result) != "result":  # metrics.json must not land in a user's folder
        raise EstimationError(
            f"{result}: not a coopmap result (no .coopmap marker of a result); evaluate writes "
            "metrics.json only into a folder that batch or isam wrote"
        )
    from estimation.app.dataset import load_dataset

    data = load_dataset(dataset)
    robots = data.robots
    if sorted(report["robots"]) != sorted(robots):
        raise EstimationError(
            f"{report_path}: robots {', '.join(sorted(report['robots']))} are not the dataset's "
            f"({', '.join(robots)}): a result of another dataset?"
        )
    grid = load_map(result / "map.npz")  # a damaged map fails before the trajectories
    metrics: dict[str, Any] = {"robots": {}}
    all_est, all_true = [], []
    estimated: dict[str, np.ndarray] = {}
    truths: dict[str, np.ndarray] = {}
    for robot in sorted(report["robots"]):
        tum = result / "poses" / f"{robot}.tum"
        if not tum.exists():  # a FIFO or a folder in its place is refused by read_tum
            metrics["robots"][robot] = {"poses": 0}
            continue
        stamps, estimate = read_tum(tum)
        truth = _truth_at(dataset, robot, stamps)
        a = ate(estimate, truth, align=False)
        entry = {"poses": len(stamps), "ate_m": a.rmse_m, "ate_deg": math.degrees(a.rmse_rad),
                 "max_m": a.max_m}  # fmt: skip
        if len(stamps) > 1:
            r = rpe(estimate, truth)
            entry.update(rpe_m=r.rmse_m, rpe_deg=math.degrees(r.rmse_rad))
        metrics["robots"][robot] = entry
        all_est.append(estimate)
        all_true.append(truth)
        estimated[robot], truths[robot] = estimate, truth
    rows = _mutual_rows(dataset, report)
    accepted = np.array([r[:2] for r in rows if r[2]]).reshape(-1, 2)
    metrics["mutual"] = {
        "events": report["observations"],
        "accepted": report["observations"] - len(report["gate_rejections"]),
        "rejected": len(report["gate_rejections"]),
        "outliers_after_gnc": len(report["outlier_factors"]),
        "median_m": float(np.median(accepted[:, 0])) if len(accepted) else None,
        "median_deg": float(np.degrees(np.median(accepted[:, 1]))) if len(accepted) else None,
        "max_m": float(accepted[:, 0].max()) if len(accepted) else None,
        "gate": _gate_table(rows),
    }
    metrics["global_localization"] = _search_errors(dataset, report.get("global_localization", {}))
    metrics["map"] = map_quality(grid, dataset / "world.yaml")
    metrics["coverage"] = _coverage(dataset, data, grid)
    metrics["timings_s"] = report["timings_s"]
    metrics["failures"] = {
        "missing_sweeps": len(report["missing_sweeps"]),
        "unseen_pairs": len(report["unseen_pairs"]),
        "dropped_poses": len(report["dropped_poses"]),
    }
    metrics["figures"] = _truth_figure(dataset, data, grid, result, estimated, truths)
    write_text_atomic(result / "metrics.json", json.dumps(metrics, indent=1) + "\n")
    return metrics


def _truth_figure(
    dataset: Path,
    data: Any,
    grid: Any,
    result: Path,
    estimated: dict[str, np.ndarray],
    truths: dict[str, np.ndarray],
) -> dict[str, str]:
    """``figures/ceiling_truth.png``: the result's ceiling band under the true world's walls,
    with each robot's estimated and true poses."""
    from estimation.app.figures import render_trajectories
    from estimation.app.rig import cut_ceiling_band

    try:
        ceiling = cut_ceiling_band(grid, data.config)
    except MapError as exc:
        return {"ceiling_truth": f"not drawn: {exc}"}
    world = load_world(dataset / "world.yaml")

    def indexed(poses: dict[str, np.ndarray]) -> dict[str, dict[int, np.ndarray]]:
        return {robot: dict(enumerate(p)) for robot, p in poses.items()}

    render_trajectories(
        ceiling, indexed(estimated), result / "figures" / "ceiling_truth.png",
        truth=indexed(truths), world=world, title="ceiling band, true walls, estimate and truth",
    )  # fmt: skip
    return {"ceiling_truth": "ceiling_truth.png"}


def _coverage(dataset: Path, data: Any, grid: Any) -> dict[str, Any]:
    """Floor coverage and rooms entered (``coverage.floor_coverage``) on the true world."""
    from estimation.app.evaluation.coverage import floor_coverage
    from estimation.app.sim.simulate import robot_free_space

    world = load_world(dataset / "world.yaml")
    truth = {r: read_tum(dataset / "ground_truth" / f"{r}.tum")[1][:, :2] for r in data.robots}
    return floor_coverage(
        world, robot_free_space(world, data.config), grid,
        [data.starts[r][:2] for r in data.robots], truth, data.config.robot.body_height_m,
    )  # fmt: skip


#: A mutual observation is "true" when its relative pose is this close to the truth.
TRUE_M, TRUE_DEG = 0.1, 1.0


def _pose_stamp(stops: dict[str, dict[int, float]], label: str) -> float:
    """The stamp of a pose label of the report ("b4"); a pose the dataset lacks is an error."""
    stamp = stops.get(label[0], {}).get(int(label[1:]))
    if stamp is None:
        raise EstimationError(f"report.json names pose {label}, which the dataset does not have")
    return stamp


def _relative_truth(
    dataset: Path, stops: dict[str, dict[int, float]], a: str, b: str
) -> np.ndarray:
    """The true T_a_b of two pose labels ("a3", "b4") at their pose stamps."""
    pa, pb = (
        _truth_at(dataset, label[0], np.array([_pose_stamp(stops, label)]))[0] for label in (a, b)
    )
    c, s = math.cos(pa[2]), math.sin(pa[2])
    dx, dy = pb[0] - pa[0], pb[1] - pa[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, pb[2] - pa[2]])


def _mutual_rows(dataset: Path, report: dict[str, Any]) -> list[tuple[float, float, bool]]:
    """(|error| m, |error| rad or NaN, accepted) of every mutual observation the gate saw."""
    from estimation.app.dataset import load_dataset, read_pose_stamps

    stops = read_pose_stamps(load_dataset(dataset))
    rows = []
    for row in report.get("mutual_observations", []):
        measured = row.get("measurement")
        if measured is None:
            rows.append((math.nan, math.nan, bool(row["accepted"])))
            continue
        truth = _relative_truth(dataset, stops, *row["pair"])
        rows.append((math.dist(measured[:2], truth[:2]),
                     abs(math.remainder(measured[2] - truth[2], 2 * math.pi)),
                     bool(row["accepted"])))  # fmt: skip
    return rows


def _gate_table(rows: list[tuple[float, float, bool]]) -> dict[str, int]:
    """The gate's decisions against the truth: a measurement is true within TRUE_M / TRUE_DEG."""
    table = {"accepted_true": 0, "accepted_false": 0, "rejected_true": 0, "rejected_false": 0,
             "rejected_without_pose": 0}  # fmt: skip
    for error_m, error_rad, accepted in rows:
        if math.isnan(error_m):
            table["rejected_without_pose" if not accepted else "accepted_false"] += 1
            continue
        true = error_m < TRUE_M and math.degrees(error_rad) < TRUE_DEG
        table[f"{'accepted' if accepted else 'rejected'}_{'true' if true else 'false'}"] += 1
    return table


def _search_errors(dataset: Path, found: dict[str, Any]) -> dict[str, Any]:
    """Errors of every search against the truth: loop-closure searches give a station's pose in
    an older station's frame; relocalizations a robot's pose in the map frame."""
    from estimation.app.dataset import load_dataset, read_pose_stamps

    stops = read_pose_stamps(load_dataset(dataset))

    def truth(label: str, at: float | None = None) -> np.ndarray:
        t = _pose_stamp(stops, label) if at is None else at
        return _truth_at(dataset, label[0], np.array([t]))[0]

    def error(pose: list[float], expected: np.ndarray) -> tuple[float, float]:
        return (math.dist(pose[:2], expected[:2]),
                abs(math.degrees(math.remainder(pose[2] - expected[2], 2 * math.pi))))  # fmt: skip

    out: dict[str, Any] = {"factors": found.get("factors", 0),
                           "validation": found.get("validation")}  # fmt: skip
    rows: dict[str, list[tuple[float, float, bool]]] = {}
    for record in found.get("searches", []):
        relative = _relative_truth(dataset, stops, record["against"], record["station"])
        kind = record.get("kind", "loop")
        rows.setdefault(kind, []).append((*error(record["pose"], relative), record["used"]))
    out["searches"] = sum(len(r) for r in rows.values())
    for kind, kind_rows in sorted(rows.items()):
        e = np.array(kind_rows, dtype=float)
        used = e[:, 2] > 0
        entry: dict[str, Any] = {"searches": len(e), "used": int(used.sum()),
                                 "median_m": float(np.median(e[:, 0])),
                                 "median_deg": float(np.median(e[:, 1]))}  # fmt: skip
        if used.any():
            u = e[used]
            within = (u[:, 0] < 0.1) & (u[:, 1] < 1.0)
            entry.update(used_median_m=float(np.median(u[:, 0])),
                         used_median_deg=float(np.median(u[:, 1])),
                         used_max_m=float(u[:, 0].max()), used_max_deg=float(u[:, 1].max()),
                         used_within_10cm_1deg=int(within.sum()))  # fmt: skip
        out[kind] = entry
    for band in ("ceiling", "floor"):
        errors = []
        for record in found.get("relocalization", []):
            if record["band"] == band:
                expected = truth(record["station"], record["time_s"] + 1.0)
                errors.append(error(record["pose"], expected))
        if errors:
            e = np.array(errors)
            ok = (e[:, 0] < 0.1) & (e[:, 1] < 1.0)
            out[f"relocalization_{band}"] = {
                "searches": len(e), "success": int(ok.sum()),
                "median_m": float(np.median(e[:, 0])), "median_deg": float(np.median(e[:, 1])),
            }  # fmt: skip
    return out
