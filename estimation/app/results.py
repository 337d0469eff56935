"""The result directory of a run (docs/design.md §12), written whole or not at all.

``poses/<robot>.tum`` (one line per pose index, stamped at an instant the robot stood still
there), ``covariances.json`` (the poses' marginal covariances), ``graph.g2o`` (vertices and
relative-pose edges with their information; the gauge as FIX), ``map.npz`` (lossless,
versioned), ``map.ply`` (occupied voxel centres), ``map.bt`` (OctoMap), ``ceiling.pgm`` +
``ceiling.yaml`` (ROS map_server), ``figures/*.png``, ``report.md``, ``report.json`` and the
effective ``config.yaml``. Everything goes to a fresh sibling folder that replaces the old
result only when all of it was written.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation import __version__
from estimation.app.config import Config, config_to_yaml
from estimation.app.rig import cut_ceiling_band
from estimation.app.workers import shared_jobs, worker_beside
from estimation.posegraph.keys import key_label, pose_key
from mapping.errors import MapError
from mapping.formats.npz import save_map
from mapping.formats.octomap_bt import write_bt
from mapping.formats.pgm import write_band_pgm
from mapping.formats.ply import write_grid_ply
from sensors.atomic import replace_directory, write_text_atomic
from sensors.trajio import G2oGraph, write_g2o, write_tum

if TYPE_CHECKING:
    from estimation.app.dataset import Sweep
    from estimation.posegraph.graph import FactorSpec
    from estimation.search.records import SearchRecord
    from mapping.grid import OccupancyGrid

__all__ = [
    "COVARIANCES_FORMAT",
    "COVARIANCES_VERSION",
    "BatchOutput",
    "covariances_json",
    "figure_worker",
    "graph_to_g2o",
    "report_markdown",
    "write_results",
]


@dataclass
class BatchOutput:
    """A run's result: poses per robot and pose index, their stamps, the sweeps, the factors
    solved and their inlier flags, the fused grid, the report (``report.json``) and the poses'
    marginal covariances (3×3, gtsam's tangent space) per robot and pose index, and the search
    records (links, loop closures, relocalizations) with the pictures of their PDFs."""

    out_dir: Path
    poses: dict[str, dict[int, np.ndarray]]
    stamps: dict[str, dict[int, float]]
    sweeps: list[Sweep]
    factors: list[FactorSpec]
    inliers: np.ndarray
    grid: OccupancyGrid
    report: dict[str, Any] = field(default_factory=dict)
    covariances: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)
    searches: list[SearchRecord] = field(default_factory=list)


def graph_to_g2o(output: BatchOutput) -> tuple[G2oGraph, dict[int, int]]:
    """The optimized graph in g2o form; vertex ids number the keys in (robot, index) order."""
    keys = sorted(
        {k for f in output.factors for k in f.keys},
        key=lambda k: key_label(k),
    )
    ids = {k: n for n, k in enumerate(keys)}
    estimate = {
        pose_key(robot, index): pose
        for robot, poses in output.poses.items()
        for index, pose in poses.items()
    }
    edges, measurements, information, fixed = [], [], [], []
    for factor, inlier in zip(output.factors, output.inliers, strict=True):
        if len(factor.keys) == 1:
            fixed.append(ids[factor.keys[0]])
            continue
        if not inlier:
            continue
        edges.append([ids[factor.keys[0]], ids[factor.keys[1]]])
        measurements.append(factor.measurement)
        information.append(np.linalg.inv(factor.covariance))
    graph = G2oGraph(
        vertex_ids=np.arange(len(keys)),
        poses=np.array([estimate.get(k, np.zeros(3)) for k in keys]).reshape(-1, 3),
        edges=np.array(edges, dtype=int).reshape(-1, 2),
        measurements=np.array(measurements).reshape(-1, 3),
        information=np.array(information).reshape(-1, 3, 3),
        fixed=tuple(sorted(set(fixed))),
    )
    return graph, ids


#: What the figure worker imports before it draws: the renderers and what their arguments are.
FIGURE_IMPORTS = (
    "estimation.app.figures",
    "matplotlib.backends.backend_agg",
    "mpl_toolkits.mplot3d",
    "estimation.search.records",
)


def figure_worker(
    figures: bool = True,
) -> contextlib.AbstractContextManager[ProcessPoolExecutor | None]:
    """The worker process that draws a result's figures beside this one (None without
    ``figures``), started on entry — its imports take about a second, best spent while this
    process fuses and writes the map — and shut down on exit."""
    return worker_beside(FIGURE_IMPORTS, figures)


def write_results(output: BatchOutput, config: Config, *, figures: bool = True,
                  worker: ProcessPoolExecutor | None = None) -> None:  # fmt: skip
    """The result folder (docs/results.md), replacing an earlier result atomically; without
    ``figures`` the folder has no ``figures/`` (drawing them is a fifth of ``batch``'s time).
    ``worker`` (:func:`figure_worker`): draws figures beside this process."""
    with replace_directory(output.out_dir, "result") as work:
        for robot, poses in output.poses.items():
            if not poses:
                continue
            indices = sorted(poses)
            stamps = np.array([output.stamps[robot].get(i, math.nan) for i in indices])
            write_tum(
                work / "poses" / f"{robot}.tum", stamps, np.array([poses[i] for i in indices])
            )
        if any(output.covariances.values()):
            write_text_atomic(work / "covariances.json", covariances_json(output))
        graph, ids = graph_to_g2o(output)
        write_g2o(work / "graph.g2o", graph)
        save_map(work / "map.npz", output.grid)
        occupied = write_grid_ply(work / "map.ply", output.grid)
        try:
            write_bt(work / "map.bt", output.grid)
        except MapError as exc:
            output.report["octomap"] = f"not written: {exc}"
        try:
            ceiling = cut_ceiling_band(output.grid, config)
            write_band_pgm(work / "ceiling.yaml", ceiling)
        except MapError as exc:
            ceiling = None
            output.report["ceiling"] = f"not written: {exc}"
        output.report["occupied_voxels"] = occupied
        output.report["g2o_vertices"] = {key_label(k): n for k, n in ids.items()}
        drawn = write_figures(output, ceiling, work / "figures", worker) if figures else None
        output.report["figures"] = drawn or {"drawn": False}
        header = f"# effective configuration; coopmap {__version__}\n"
        write_text_atomic(work / "config.yaml", header + config_to_yaml(config))
        write_text_atomic(work / "report.md", report_markdown(output))
        write_text_atomic(
            work / "report.json", json.dumps(output.report, indent=1, default=float) + "\n"
        )


#: At most this many search PDFs are drawn per result (the relocalizations in the ceiling band
#: first, then the loop closures that became factors, then the others, each in mission order):
#: each takes about 0.25 s.
MAX_PDF_FIGURES = 6


def _pdf_figures(searches: list[SearchRecord]) -> list[tuple[str, SearchRecord]]:
    """The search records whose PDF a result draws, with their file names (relocalizations in
    the floor band, reported for comparison, are not drawn)."""
    drawn = [r for r in searches if r.picture is not None and r.band == "ceiling"]
    order = {"relocalize": 0, "loop": 1}
    drawn.sort(key=lambda r: (order.get(r.kind, 2), not r.used, r.time_s))
    names = []
    for record in drawn[:MAX_PDF_FIGURES]:
        kind = "relocalization" if record.kind == "relocalize" else record.kind
        names.append((f"pdf_{kind}_{record.station}_{record.against}_{record.band}.png", record))
    return names


def _used(record: SearchRecord) -> str:
    if record.kind == "relocalize":
        return " (reported, not a factor)"
    return ", a factor" if record.used else ", not used"


def write_figures(output: BatchOutput, ceiling: Any, figures: Path,
                  worker: ProcessPoolExecutor | None = None) -> dict[str, Any]:  # fmt: skip
    """A result's figures: the ceiling band with the trajectories, the occupied cells (paper
    Fig. 5a), the first sweep as measured (Fig. 4b) and the search PDFs (Fig. 5b); returns what
    was drawn for ``report.json``. With ``worker`` (:func:`~estimation.app.workers.spawn_worker`)
    all but the occupied cells (the whole grid) are drawn by it and this process side by side."""
    from estimation.app.figures import (
        render_map_cubes,
        render_search_pdf,
        render_sweep,
        render_trajectories,
    )

    drawn: dict[str, Any] = {"drawn": True}
    here = [functools.partial(render_map_cubes, output.grid, figures / "map_cubes.png")]
    drawn["map"] = "map_cubes.png"
    shared = []
    if ceiling is not None:
        shared.append(functools.partial(render_trajectories, ceiling, output.poses,
                                        figures / "ceiling_trajectories.png"))  # fmt: skip
        drawn["ceiling"] = "ceiling_trajectories.png"
    if output.sweeps:
        sweep = output.sweeps[0]
        beacons = np.array([d.center_scanner for d in sweep.detections]).reshape(-1, 3)
        title = f"sweep of {sweep.robot}{sweep.index} (dwell {sweep.dwell})"
        shared.append(functools.partial(render_sweep, sweep.points_scanner, figures / "sweep.png",
                                        beacons=beacons, title=title))  # fmt: skip
        drawn["sweep"] = {"file": "sweep.png", "pose": f"{sweep.robot}{sweep.index}"}
    pdfs = []
    for name, record in _pdf_figures(output.searches):
        kind = {"relocalize": "relocalization", "loop": "loop closure"}.get(record.kind, "link")
        title = (f"{kind}: {record.station} against {record.against} ({record.band} band), "
                 f"peak ratio {record.peak_ratio:.3g}" + _used(record))  # fmt: skip
        shared.append(functools.partial(render_search_pdf, record.picture, np.array(record.pose),
                                        figures / name, title=title))  # fmt: skip
        pdfs.append(name)
    shared_jobs(here, shared, worker)
    drawn["pdfs"] = pdfs
    drawn["pdfs_not_drawn"] = len(
        [r for r in output.searches if r.picture is not None and r.band == "ceiling"]
    ) - len(pdfs)
    return drawn


#: ``covariances.json``: its format name and version.
COVARIANCES_FORMAT, COVARIANCES_VERSION = "coopmap.covariances", 1


def covariances_json(output: BatchOutput) -> str:
    """``covariances.json``: per robot, the pose indices of ``poses/<robot>.tum`` (line by line)
    and each pose's 3×3 marginal covariance in gtsam's tangent space of the pose (x_m, y_m
    along the robot's axes, yaw_rad)."""
    robots = {}
    for robot, poses in output.poses.items():
        indices = [i for i in sorted(poses) if i in output.covariances.get(robot, {})]
        if indices:
            robots[robot] = {
                "indices": indices,
                "covariances": [output.covariances[robot][i].tolist() for i in indices],
            }
    document = {
        "format": COVARIANCES_FORMAT,
        "version": COVARIANCES_VERSION,
        "frame": "tangent space of each pose: x_m, y_m along the robot's axes, yaw_rad",
        "robots": robots,
    }
    return json.dumps(document, indent=1) + "\n"


def report_markdown(output: BatchOutput, metrics: dict[str, Any] | None = None) -> str:
    r = output.report
    lines = [
        "# coopmap result",
        "",
        f"Dataset `{r['dataset']}`, coopmap {r['coopmap']}.",
        "",
        "| robot | poses | telegrams | checksum failures | undecodable | implausible scans "
        "| bytes skipped |",
        "|---|---|---|---|---|---|---|",
    ]
    for robot, s in r["robots"].items():
        lines.append(
            f"| {robot} | {s['poses']} | {s['telegrams']} | {s['checksum_failures']} | "
            f"{s['undecodable']} | {s.get('implausible_scans', 0)} | {s['bytes_skipped']} |"
        )
    lines += [
        "",
        f"* dwells: {r['dwells']}, sweeps: {r['sweeps']}, mutual observations: {r['observations']}",
        f"* factors: {r['factors']}, rejected by the gate: {len(r['gate_rejections'])}, "
        f"outliers after GNC: {len(r['outlier_factors'])}",
        f"* occupied voxels: {r.get('occupied_voxels', 0)}",
        f"* missing sweeps: {len(r['missing_sweeps'])}; pairs without a beacon: "
        f"{len(r['unseen_pairs'])}; poses not connected to the map: {len(r['dropped_poses'])}",
        "",
        "Timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in r["timings_s"].items()),
        "",
    ]
    figures = r.get("figures", {})
    if "ceiling" in figures:
        lines += [f"![ceiling band and trajectories](figures/{figures['ceiling']})", ""]
    if "map" in figures:
        lines += [f"![occupied cells](figures/{figures['map']})", ""]
    if "sweep" in figures:
        lines += [f"![one measured sweep](figures/{figures['sweep']['file']})", ""]
    for name in figures.get("pdfs", []):
        lines += [f"![search PDF](figures/{name})", ""]
    return "\n".join(lines)
