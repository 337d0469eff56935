"""``coopmap bench search``: the exhaustive search against the paper's per-pose loop, one run.

The map is a synthetic 20 m × 20 m floor of rooms (``scenes.random_building``) at the
configured resolution (0.1 m: 200 × 200 cells); the local grid is the band a robot maps within
8 m of itself, with occupancy noise, flipped and dropped cells. coopmap scores every pose of
the whole map — 200 × 200 positions × 360 rotations at 1° — and returns the whole normalised
PDF with its refined peak, covariance and dominance. The peer is the per-pose loop (transform
the local cells, look up the map cells, sum), the paper's method: it would take hours here, so
it is timed on a subset — ``peer_rotations`` rotations spread over the circle, every
``peer_row_stride``-th row of positions — and extrapolated by the number of poses; its scores
on that subset are checked against coopmap's.

The best pose alone is timed too: branch and bound (``search.bnb``), exact — its lattice pose
and score are checked against the full search's — with the pruning it achieved; and beside the
full search on cases where the bounds prune little (``PRUNING_CASES``: a 4 m view on a 10 m and
on a 40 m map), where it must hand over to the FFT early enough never to be the slower.

**Coarse to fine** (``run_coarse_to_fine_case``): an office floor (``scenes.office_floor``,
corridors every 12 m, rooms, fixtures) of 100 m × 100 m at 0.1 m with 360 rotations — 360 M
poses, beyond the whole PDF — searched by ``search_coarse_to_fine``: wall time, peak memory
(numpy's allocations by tracemalloc, and the process's peak RSS), the pose found against the
truth; and on a 40 m floor, where the exhaustive search also runs, both searches' lattice poses
and how close their PDFs are.
"""

from __future__ import annotations

import math
import resource
import statistics
import time
import tracemalloc
from dataclasses import replace
from typing import Any

import numpy as np

from estimation.search.bnb import lattice_best
from estimation.search.correlate import correlate_all, score_poses_loop
from estimation.search.exhaustive import SearchParams, best_pose, search
from estimation.search.lattice import match_values
from estimation.search.pyramid import TiledResult, search_coarse_to_fine
from estimation.search.scenes import local_view, office_floor, random_building, rasterise

__all__ = ["compare_best_pose", "run_coarse_to_fine_case", "run_search_benchmark"]

MAP_SIDE_M = 20.0
LOCAL_RADIUS_M = 8.0
TRUE_POSE = np.array([8.37, 11.21, math.radians(37.4)])
#: (name, map side m, view radius m) of the best-pose-versus-full-search comparison, besides the
#: benchmark's own 20 m map with its 8 m view.
PRUNING_CASES = (("10 m map, 4 m view", 10.0, 4.0), ("40 m map, 4 m view", 40.0, 4.0))


def _bounded(params: SearchParams) -> SearchParams:
    """The yardsticks time the branch and bound, which bounds one correlation: the
    ``agreement`` score (``excess`` costs a second correlation per rotation, see §7)."""
    return params if params.score != "excess" else replace(params, score="agreement")


def compare_best_pose(
    name: str, side_m: float, radius_m: float, params: SearchParams, resolution_m: float,
    repeats: int, seed: int,
) -> dict[str, Any]:  # fmt: skip
    """Full search and best pose alone on one generated building: medians and maxima."""
    params = _bounded(params)
    rng = np.random.default_rng(seed)
    scene = random_building(rng, side_m)
    cells = round(side_m / resolution_m)
    global_ = rasterise(scene, np.zeros(3), (0.0, 0.0), (cells, cells), resolution_m)
    truth = np.array([0.42 * side_m, 0.56 * side_m, math.radians(37.4)])
    local = local_view(scene, truth, radius_m, resolution_m, rng, noise=0.1,
                       drop_fraction=0.2, flip_fraction=0.02)  # fmt: skip
    search(local, global_, params)  # warm-up
    full = [search(local, global_, params) for _ in range(repeats)]
    best_pose(local, global_, params)
    best = [best_pose(local, global_, params) for _ in range(repeats)]
    tolerance = 1e-6 * float(np.abs(match_values(local, params.metric)).sum())
    same = abs(best[0][1] - full[0].best_score) <= tolerance
    return _comparison(name, [r.seconds for r in full], [b[2] for b in best], same)


def _comparison(
    name: str, full_s: list[float], best_s: list[float], same_score: bool
) -> dict[str, Any]:
    return {
        "case": name,
        "full_seconds": statistics.median(full_s),
        "full_seconds_max": max(full_s),
        "best_pose_seconds": statistics.median(best_s),
        "best_pose_seconds_max": max(best_s),
        "best_over_full": statistics.median(best_s) / statistics.median(full_s),
        "same_score": bool(same_score),
    }


def run_search_benchmark(
    params: SearchParams,
    resolution_m: float = 0.1,
    *,
    repeats: int = 5,
    peer_rotations: int = 2,
    peer_row_stride: int = 10,
    seed: int = 0,
) -> dict[str, Any]:
    """Time coopmap's search (median of ``repeats`` after a warm-up) and the per-pose loop on a
    subset of the poses; return the figures of docs/design.md §11 and the details."""
    params = _bounded(params)
    rng = np.random.default_rng(seed)
    scene = random_building(rng, MAP_SIDE_M)
    cells = round(MAP_SIDE_M / resolution_m)
    global_ = rasterise(scene, np.zeros(3), (0.0, 0.0), (cells, cells), resolution_m)
    local = local_view(
        scene,
        TRUE_POSE,
        LOCAL_RADIUS_M,
        resolution_m,
        rng,
        noise=0.1,
        drop_fraction=0.2,
        flip_fraction=0.02,
    )

    search(local, global_, params)  # warm-up: compiled kernels, first touch of the memory
    seconds, pdf_seconds = [], []
    for _ in range(repeats):
        result = search(local, global_, params)
        seconds.append(result.seconds)
        begin = time.perf_counter()
        pdf = result.pdf
        pdf_seconds.append(time.perf_counter() - begin)
        del pdf
    best_pose(local, global_, params)  # warm-up
    best_seconds = []
    for _ in range(repeats):
        pose, best_score, took = best_pose(local, global_, params)
        best_seconds.append(took)
    pruning = lattice_best(
        local, global_, result.x_m, result.y_m, result.yaw_rad, params.metric, params.thread_count()
    )
    error = result.pose - TRUE_POSE
    error_deg = abs(math.degrees((error[2] + math.pi) % (2 * math.pi) - math.pi))

    # The peer on a subset of the poses; the same subset of coopmap's scores to compare.
    picks = np.linspace(0, len(result.yaw_rad), peer_rotations, endpoint=False).astype(int)
    rows = np.arange(0, len(result.y_m), peer_row_stride)
    yaws, ys = result.yaw_rad[picks], result.y_m[rows]
    begin = time.perf_counter()
    peer_scores = score_poses_loop(local, global_, result.x_m, ys, yaws, params.metric)
    peer_measured = time.perf_counter() - begin
    poses = result.poses
    peer_poses = peer_scores.size
    peer_seconds = peer_measured * poses / peer_poses
    ours = correlate_all(local, global_, result.x_m, result.y_m, yaws, params.metric)[:, rows]
    scale = float(np.abs(match_values(local, params.metric)).sum())

    median = statistics.median(seconds)
    scale_tolerance = 1e-6 * scale
    cases = [
        _comparison(f"{MAP_SIDE_M:g} m map, {LOCAL_RADIUS_M:g} m view (the benchmark)", seconds,
                    best_seconds, abs(best_score - result.best_score) <= scale_tolerance),
        *(compare_best_pose(name, side, radius, params, resolution_m, min(repeats, 3), seed)
          for name, side, radius in PRUNING_CASES),
    ]  # fmt: skip
    return {
        "benchmark": "search",
        "ratio": peer_seconds / median,
        "seconds": median,
        "peer_seconds": peer_seconds,
        "best_pose_seconds": statistics.median(best_seconds),
        "best_pose_seconds_max": max(best_seconds),
        "seconds_max": max(seconds),
        "posepdf_seconds": statistics.median(pdf_seconds),
        "peer_seconds_measured": peer_measured,
        "peer_poses_timed": peer_poses,
        "peer_rotations_timed": len(yaws),
        "peer_max_score_difference": float(np.abs(ours - peer_scores).max()) / scale,
        "map_cells": [cells, cells],
        "local_known_cells": int(np.count_nonzero(match_values(local, params.metric))),
        "poses": poses,
        "rotations": len(result.yaw_rad),
        "resolution_m": resolution_m,
        "repeats": repeats,
        "error_m": float(math.hypot(error[0], error[1])),
        "error_deg": error_deg,
        "best_pose_error_m": float(math.hypot(*(pose - TRUE_POSE)[:2])),
        "best_pose_same_lattice_pose": pruning.index == result.best_index,
        "best_pose_score_difference": abs(best_score - result.best_score) / scale,
        "best_pose_pose_difference_m": float(math.hypot(*(pose - result.pose)[:2])),
        "best_pose_blocks": pruning.blocks,
        "best_pose_blocks_expanded": pruning.blocks_expanded,
        "best_pose_quarters_scored": pruning.quarters_scored,
        "best_pose_rotations_expanded": pruning.rotations_expanded,
        "best_pose_pruned": pruning.pruned,
        "peak_ratio": result.peak_ratio,
        "workers": params.thread_count(),
        "best_pose_cases": cases,
    }


def _dense_evaluated(result: TiledResult) -> np.ndarray:
    out = np.zeros((len(result.yaw_rad), len(result.y_m), len(result.x_m)), dtype=bool)
    for p in result.patches:
        _, rows, cols = p.mask.shape
        out[p.t, p.y0 : p.y0 + rows, p.x0 : p.x0 + cols] |= p.mask
    return out


def run_coarse_to_fine_case(
    params: SearchParams,
    side_m: float = 100.0,
    radius_m: float = 8.0,
    resolution_m: float = 0.1,
    *,
    repeats: int = 3,
    compare: bool = False,
    seed: int = 0,
) -> dict[str, Any]:
    """The coarse-to-fine search on a generated office floor of ``side_m`` (first run, then the
    median of ``repeats``; peak memory on one more run), and, with ``compare``, the exhaustive
    search on the same lattice beside it."""
    rng = np.random.default_rng(seed)
    scene = office_floor(rng, side_m)
    cells = round(side_m / resolution_m)
    global_ = rasterise(scene, np.zeros(3), (0.0, 0.0), (cells, cells), resolution_m)
    truth = np.array([0.4237 * side_m, 0.5621 * side_m, math.radians(37.4)])
    local = local_view(scene, truth, radius_m, resolution_m, rng, noise=0.1,
                       drop_fraction=0.2, flip_fraction=0.02)  # fmt: skip
    first = search_coarse_to_fine(local, global_, params)
    runs = [search_coarse_to_fine(local, global_, params) for _ in range(repeats)]
    tracemalloc.start()
    result = search_coarse_to_fine(local, global_, params)
    traced = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    error = result.pose - truth
    report: dict[str, Any] = {
        "side_m": side_m,
        "radius_m": radius_m,
        "poses": result.poses,
        "poses_evaluated": result.poses_evaluated,
        "patches": len(result.patches),
        "coarse_factor": result.coarse_factor,
        "local_known_cells": int(np.count_nonzero(match_values(local, params.metric))),
        "first_seconds": first.seconds,
        "seconds": statistics.median(r.seconds for r in runs),
        "seconds_max": max(r.seconds for r in runs),
        "repeats": repeats,
        "peak_numpy_bytes": traced,
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "unevaluated_mass": result.unevaluated_mass,
        "peak_ratio": result.peak_ratio,
        "pose": [float(v) for v in result.pose],
        "truth": [float(v) for v in truth],
        "error_m": float(math.hypot(error[0], error[1])),
        "error_deg": abs(math.degrees((error[2] + math.pi) % (2 * math.pi) - math.pi)),
    }
    if compare:
        search(local, global_, params)  # warm-up
        whole = [search(local, global_, params) for _ in range(repeats)]
        full = whole[-1]
        inside = _dense_evaluated(result)
        dense = result.dense_prob()
        report |= {
            "exhaustive_seconds": statistics.median(w.seconds for w in whole),
            "same_lattice_pose": result.best_index == full.best_index,
            "pose_difference_m": float(math.hypot(*(result.pose - full.pose)[:2])),
            "exhaustive_mass_outside": float(full.prob[~inside].sum(dtype=np.float64)),
            "total_variation": 0.5 * float(np.abs(dense - full.prob).sum(dtype=np.float64)),
            "exhaustive_peak_ratio": full.peak_ratio,
        }
    return report
