"""``coopmap evaluate``: a result against its dataset's ground truth → ``metrics.json``.

* Trajectories: the pose of every (robot, index) in ``poses/<robot>.tum`` against the true pose
  at the same stop (``ground_truth/<robot>.tum``). The gauge is the first robot's declared start,
  so estimate and truth share the map frame: ATE is computed without alignment (RMS of position
  and heading errors); RPE over consecutive poses of each robot.
* Mutual localization: every mutual factor's relative pose against the true relative pose; the
  gate's rejections and GNC's outliers are counted.
* Map: occupied cells (P > the grid's threshold) against the voxels the world's surfaces pass
  through (``sensors.sim.truth``), at the map's resolution. Precision: the share of occupied
  cells within one cell of a true surface voxel; recall: the share of true surface voxels the
  map observed (known, occupied or free) that are within one cell of an occupied cell.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from estimation.errors import EstimationError
from estimation.metrics import ate, rpe
from estimation.trajio import read_tum
from mapping.npz import load_map
from sensors.atomic import write_text_atomic
from sensors.sim.scene import build_mesh
from sensors.sim.truth import surface_voxels
from sensors.sim.world import load_world

__all__ = ["evaluate", "map_quality"]


def _truth_at(dataset: Path, robot: str, stamps: np.ndarray) -> np.ndarray:
    path = dataset / "ground_truth" / f"{robot}.tum"
    if not path.is_file():
        raise EstimationError(f"{dataset}: no ground truth for robot {robot!r} ({path.name})")
    t, poses = read_tum(path)
    # Robots stand still after each stop: half a second later is safely the stop's pose.
    query = stamps + 0.5
    yaw = np.unwrap(poses[:, 2])
    return np.column_stack(
        [
            np.interp(query, t, poses[:, 0]),
            np.interp(query, t, poses[:, 1]),
            np.interp(query, t, yaw),
        ]
    )


def _dilate(keys: set[tuple[int, int, int]]) -> set[tuple[int, int, int]]:
    out = set()
    for i, j, k in keys:
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                for dk in (-1, 0, 1):
                    out.add((i + di, j + dj, k + dk))
    return out


def map_quality(grid: Any, world_path: Path) -> dict[str, Any]:
    """Precision and recall of the occupied cells against the world's surface voxels."""
    world = load_world(world_path)
    params = grid.params
    truth = surface_voxels(build_mesh(world), params.resolution_m, np.asarray(params.origin_m))
    true_cells = {tuple(c) for c in truth.indices.tolist()}
    occupied, _ = grid.occupied()
    occupied_cells = {tuple(c) for c in np.asarray(occupied).tolist()}
    if not occupied_cells:
        return {"resolution_m": params.resolution_m, "precision": 0.0, "recall": 0.0, "occupied": 0}
    near_truth = _dilate(true_cells)
    near_map = _dilate(occupied_cells)
    precision = sum(c in near_truth for c in occupied_cells) / len(occupied_cells)
    known_cells, _ = grid.cells()
    known = {tuple(c) for c in np.asarray(known_cells).tolist()}
    observed_truth = [c for c in true_cells if c in known]
    recall = sum(c in near_map for c in observed_truth) / max(1, len(observed_truth))
    return {
        "resolution_m": params.resolution_m,
        "precision": precision,
        "recall": recall,
        "occupied": len(occupied_cells),
        "true_surface_voxels_observed": len(observed_truth),
        "true_surface_voxels": len(true_cells),
    }


def evaluate(dataset_dir: Path | str, result_dir: Path | str | None = None) -> dict[str, Any]:
    dataset = Path(dataset_dir)
    result = Path(result_dir) if result_dir is not None else dataset / "result"
    report_path = result / "report.json"
    if not report_path.is_file():
        raise EstimationError(f"{result}: no result here (report.json missing): run coopmap batch")
    report = json.loads(report_path.read_text(encoding="utf-8"))
    metrics: dict[str, Any] = {"robots": {}}
    all_est, all_true = [], []
    for robot in sorted(report["robots"]):
        tum = result / "poses" / f"{robot}.tum"
        if not tum.is_file():
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
    errors = _mutual_errors(dataset, result)
    metrics["mutual"] = {
        "events": report["observations"],
        "accepted": report["observations"] - len(report["gate_rejections"]),
        "rejected": len(report["gate_rejections"]),
        "outliers_after_gnc": len(report["outlier_factors"]),
        "median_m": float(np.median(errors[:, 0])) if len(errors) else None,
        "median_deg": float(np.degrees(np.median(errors[:, 1]))) if len(errors) else None,
        "max_m": float(errors[:, 0].max()) if len(errors) else None,
    }
    metrics["global_localization"] = _search_errors(dataset, report.get("global_localization", {}))
    metrics["map"] = map_quality(load_map(result / "map.npz"), dataset / "world.yaml")
    metrics["timings_s"] = report["timings_s"]
    metrics["failures"] = {
        "missing_sweeps": len(report["missing_sweeps"]),
        "unseen_pairs": len(report["unseen_pairs"]),
        "dropped_poses": len(report["dropped_poses"]),
    }
    write_text_atomic(result / "metrics.json", json.dumps(metrics, indent=1) + "\n")
    return metrics


def _mutual_errors(dataset: Path, result: Path) -> np.ndarray:
    """|error| (m, rad) of each mutual edge of graph.g2o against the true relative pose."""
    from estimation.pipeline import load_dataset
    from estimation.trajio import read_g2o

    graph_path = result / "graph.g2o"
    if not graph_path.is_file():
        return np.zeros((0, 2))
    report = json.loads((result / "report.json").read_text(encoding="utf-8"))
    labels = {v: k for k, v in report.get("g2o_vertices", {}).items()}
    data = load_dataset(dataset)
    stops = {robot: data.stop_times(robot) for robot in data.robots}
    graph = read_g2o(graph_path)
    out = []
    for (i, j), measured in zip(graph.edges, graph.measurements, strict=True):
        li, lj = labels.get(int(i)), labels.get(int(j))
        if li is None or lj is None or li[0] == lj[0]:
            continue  # odometry edges join poses of one robot
        a, b = (
            _truth_at(dataset, label[0], np.array([stops[label[0]][int(label[1:])]]))[0]
            for label in (li, lj)
        )
        c, s = math.cos(a[2]), math.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        true_rel = np.array([c * dx + s * dy, -s * dx + c * dy, b[2] - a[2]])
        out.append([math.hypot(*(measured[:2] - true_rel[:2])),
                    abs(math.remainder(measured[2] - true_rel[2], 2 * math.pi))])  # fmt: skip
    return np.array(out).reshape(-1, 2)


def _search_errors(dataset: Path, found: dict[str, Any]) -> dict[str, Any]:
    """Errors of every search against the truth: loop-closure searches give a station's pose in
    an older station's frame; relocalizations a robot's pose in the map frame."""
    from estimation.pipeline import load_dataset

    data = load_dataset(dataset)
    stops = {robot: data.stop_times(robot) for robot in data.robots}

    def truth(label: str, at: float | None = None) -> np.ndarray:
        t = stops[label[0]][int(label[1:])] if at is None else at
        return _truth_at(dataset, label[0], np.array([t]))[0]

    def error(pose: list[float], expected: np.ndarray) -> tuple[float, float]:
        return (math.dist(pose[:2], expected[:2]),
                abs(math.degrees(math.remainder(pose[2] - expected[2], 2 * math.pi))))  # fmt: skip

    out: dict[str, Any] = {"factors": found.get("factors", 0)}
    rows = []
    for record in found.get("searches", []):
        a, b = truth(record["against"]), truth(record["station"])
        c, s = math.cos(a[2]), math.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        relative = np.array([c * dx + s * dy, -s * dx + c * dy, b[2] - a[2]])
        rows.append((*error(record["pose"], relative), record["used"]))
    out["searches"] = len(rows)
    if rows:
        e = np.array(rows, dtype=float)
        used = e[:, 2] > 0
        out.update(
            median_m=float(np.median(e[:, 0])),
            median_deg=float(np.median(e[:, 1])),
            max_m=float(e[:, 0].max()),
            max_deg=float(e[:, 1].max()),
            used=int(used.sum()),
            used_max_m=float(e[used, 0].max()) if used.any() else None,
        )
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
