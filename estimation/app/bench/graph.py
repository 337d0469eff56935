"""``coopmap bench graph``: batch and iSAM2 on synthetic and real pose graphs (docs/design.md
§10–11).

Cases:

* ``leapfrog_5000`` — a synthetic two-robot leapfrog mission (``estimation.posegraph.synthetic``):
  500 stations × 10 poses, mutual observations, odometry, and every station globally localized
  against a fixed prior map; fed event by event through the graph builder (gates included);
* ``leapfrog_5000_loops`` — the same mission without a prior map: stations are localized
  against the stations of earlier laps (loop-closure between-factors), the hard case for iSAM2;
* ``intel`` and ``ais2klinik`` — the real g2o graphs of ``../shared/data/pose_graphs_g2o``
  (Intel Research Lab, D. Hähnel; AIS2Klinik, Freiburg), fed vertex by vertex: each vertex with
  the edges that reach back to earlier vertices. Where iSAM2's Cholesky factorization declares
  an increment indeterminate (ais2klinik), the case is rerun with QR and says so.

Per case: batch seconds (``optimize_batch``, robust "none": LM from the better of the initial
guesses and LAGO — the problem iSAM2 solves), on the synthetic missions also the seconds of the
configured robust mode (GNC-TLS) and its outliers; iSAM2 time per event (median, p99, max), in
wall clock and in process CPU time; the Python overhead per event measured separately (builder,
GTSAM object construction); final errors (GTSAM graph error; ATE against the truth where there is
one); the largest batch–iSAM2 difference; and the peer: re-solving the graph so far with batch
LM after an event — what an online system without iSAM2 would do — timed warm-started at five
points of the stream. ``ratio`` is the peer's time per event over iSAM2's (update plus Python).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import gtsam
import numpy as np

from estimation.app.evaluation.metrics import align_se2, ate
from estimation.app.resources import DATA_DIR
from estimation.errors import EstimationError
from estimation.posegraph.graph import FactorSpec, GraphSettings
from estimation.posegraph.gtsam_factors import to_gtsam_graph, to_gtsam_values
from estimation.posegraph.smoother import (
    IncrementalSmoother,
    RobustMode,
    extract_poses,
    optimize_batch,
)
from estimation.posegraph.synthetic import Scenario, leapfrog
from sensors.geometry import se2
from sensors.trajio import G2oGraph, read_g2o

__all__ = [
    "CASES",
    "CaseResult",
    "Difference",
    "format_report",
    "leapfrog_5000",
    "pose_difference",
    "run_bench",
    "run_g2o_case",
    "run_leapfrog_case",
]

#: ``../shared/data`` beside the repository root.
CASES = ("leapfrog_5000", "leapfrog_5000_loops", "intel", "ais2klinik")
_PEER_SAMPLES = 5
#: The gauge prior on a g2o graph's first vertex: stiff, but not so stiff that it alone ruins the
#: conditioning of a long chain (1e-6 made iSAM2 fail on ais2klinik).
_GAUGE_SIGMA = 1e-3

Progress = Callable[[str], None]


def leapfrog_5000(
    seed: int = 0, loops: bool = False, settings: GraphSettings | None = None
) -> Scenario:
    """The benchmark mission: 500 stations × (1 + 9 scan poses) = 5,000 poses."""
    if loops:
        return leapfrog(500, 9, seed=seed, settings=settings, map_prior_every=0, loop_closures=True)
    return leapfrog(500, 9, seed=seed, settings=settings, map_prior_every=1, loop_closures=False)


@dataclass(frozen=True)
class CaseResult:
    """The figures of one case (times in seconds or milliseconds as named)."""

    name: str
    poses: int
    factors: int
    events: int
    batch_seconds: float
    isam2_seconds: float
    isam2_update_median_ms: float
    isam2_update_p99_ms: float
    isam2_update_max_ms: float
    python_overhead_median_ms: float
    python_overhead_p99_ms: float
    event_p99_ms: float
    isam2_update_cpu_median_ms: float
    isam2_update_cpu_p99_ms: float
    event_cpu_p99_ms: float
    reeliminated_median: float  # variables iSAM2 eliminated again per event: the update's work
    reeliminated_p99: float
    batch_error: float
    isam2_error: float
    max_difference_mm: float  # raw: as estimated, each in its own gauge
    max_difference_deg: float
    aligned_difference_mm: float  # after aligning the gauges (Difference)
    aligned_difference_deg: float
    gauge_m: float
    gauge_deg: float
    peer_update_ms: float
    ratio: float
    ate_batch_m: float | None = None
    ate_isam2_m: float | None = None
    factorization: str = "CHOLESKY"
    robust_mode: str | None = None
    robust_seconds: float | None = None
    robust_outliers: int | None = None


def _stats(seconds: Sequence[float]) -> tuple[float, float, float]:
    ms = np.asarray(seconds) * 1e3
    return float(np.median(ms)), float(np.percentile(ms, 99)), float(ms.max())


@dataclass(frozen=True)
class Difference:
    """Batch against iSAM2: the largest pose difference as estimated (``raw``) and after
    aligning iSAM2's estimate onto batch's by the SE(2) transform that minimises the position
    differences (``aligned``; Umeyama without scale) — the gauge, which a prior on one pose
    fixes only as firmly as its noise allows, taken out; ``gauge`` is that transform."""

    raw_mm: float
    raw_deg: float
    aligned_mm: float
    aligned_deg: float
    gauge_m: float  # |translation| of T_batch_isam2
    gauge_deg: float  # its rotation


def _largest(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    d = a - b
    return (
        float(np.hypot(d[:, 0], d[:, 1]).max() * 1e3),
        float(np.degrees(np.abs(se2.wrap_angle(d[:, 2])).max())),
    )


def pose_difference(batch: dict[int, np.ndarray], isam2: dict[int, np.ndarray]) -> Difference:
    """:class:`Difference` of two estimates of the same poses (keyed alike)."""
    keys = sorted(batch)
    a = np.array([batch[k] for k in keys])
    b = np.array([isam2[k] for k in keys])
    T_a_b = align_se2(b, a)
    raw, aligned = _largest(a, b), _largest(a, se2.compose(T_a_b, b))
    return Difference(*raw, *aligned, float(np.hypot(*T_a_b[:2])),
                      float(np.degrees(abs(se2.wrap_angle(T_a_b[2])))))  # fmt: skip


def _peer_ms(
    graphs: Sequence[gtsam.NonlinearFactorGraph], estimate: dict[int, np.ndarray]
) -> float:
    """Mean time of a warm-started batch LM re-solve of growing prefixes of the graph."""
    times = []
    for graph in graphs:
        keys = {int(k) for k in graph.keyVector()}
        values = to_gtsam_values({k: estimate[k] for k in keys})
        start = time.perf_counter()
        gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        times.append(time.perf_counter() - start)
    return float(np.mean(times) * 1e3)


def run_leapfrog_case(
    name: str,
    scenario: Scenario,
    settings: GraphSettings,
    robust: RobustMode = "gnc_tls",
    relinearize_threshold: float = 0.01,
    relinearize_skip: int = 1,
) -> CaseResult:
    """Batch and iSAM2 over a synthetic mission, through the graph builder."""
    smoother = IncrementalSmoother(settings, relinearize_threshold, relinearize_skip)
    start = time.perf_counter()
    counts = []
    for event in scenario.events:
        smoother.add(event)
        counts.append(len(smoother.builder.factors))
    isam2_seconds = time.perf_counter() - start
    isam2_estimate = smoother.estimate()
    builder = smoother.builder
    # The same problem as iSAM2 (no GNC), then GNC on it, timed apart.
    batch = optimize_batch(builder.factors, builder.initial_values(), robust="none")
    robust_batch = optimize_batch(builder.factors, builder.initial_values(), robust=robust)
    keys = sorted(batch.estimate)
    truth = scenario.truth_array(keys)
    samples = [counts[int(len(counts) * (i + 1) / _PEER_SAMPLES) - 1] for i in range(_PEER_SAMPLES)]
    prefixes = [to_gtsam_graph(builder.factors[:n]) for n in samples]
    full = to_gtsam_graph(builder.factors)
    return _result(
        name,
        poses=len(keys),
        factors=len(builder.factors),
        update_seconds=smoother.update_seconds,
        python_seconds=smoother.python_seconds,
        update_cpu=smoother.update_cpu_seconds,
        python_cpu=smoother.python_cpu_seconds,
        reeliminated=smoother.reeliminated,
        isam2_seconds=isam2_seconds,
        batch_seconds=batch.seconds,
        batch_error=float(full.error(to_gtsam_values(batch.estimate))),
        isam2_error=float(full.error(to_gtsam_values(isam2_estimate))),
        difference=pose_difference(batch.estimate, isam2_estimate),
        peer_ms=_peer_ms(prefixes, batch.estimate),
        ate_batch=ate(np.array([batch.estimate[k] for k in keys]), truth, align=False).rmse_m,
        ate_isam2=ate(np.array([isam2_estimate[k] for k in keys]), truth, align=False).rmse_m,
        robust=(robust, robust_batch.seconds, len(robust_batch.outliers)),
    )


def _result(
    name: str,
    *,
    poses: int,
    factors: int,
    update_seconds: Sequence[float],
    python_seconds: Sequence[float],
    update_cpu: Sequence[float],
    python_cpu: Sequence[float],
    reeliminated: Sequence[int],
    isam2_seconds: float,
    batch_seconds: float,
    batch_error: float,
    isam2_error: float,
    difference: Difference,
    peer_ms: float,
    ate_batch: float | None = None,
    ate_isam2: float | None = None,
    factorization: str = "CHOLESKY",
    robust: tuple[str, float, int] | None = None,
) -> CaseResult:
    median, p99, worst = _stats(update_seconds)
    py_median, py_p99, _ = _stats(python_seconds)
    per_event = np.asarray(update_seconds) + np.asarray(python_seconds)
    _, event_p99, _ = _stats(per_event)
    cpu_median, cpu_p99, _ = _stats(update_cpu)
    _, event_cpu_p99, _ = _stats(np.asarray(update_cpu) + np.asarray(python_cpu))
    return CaseResult(
        name=name,
        poses=poses,
        factors=factors,
        events=len(update_seconds),
        batch_seconds=batch_seconds,
        isam2_seconds=isam2_seconds,
        isam2_update_median_ms=median,
        isam2_update_p99_ms=p99,
        isam2_update_max_ms=worst,
        python_overhead_median_ms=py_median,
        python_overhead_p99_ms=py_p99,
        event_p99_ms=event_p99,
        isam2_update_cpu_median_ms=cpu_median,
        isam2_update_cpu_p99_ms=cpu_p99,
        event_cpu_p99_ms=event_cpu_p99,
        reeliminated_median=float(np.percentile(reeliminated, 50)) if len(reeliminated) else 0.0,
        reeliminated_p99=float(np.percentile(reeliminated, 99)) if len(reeliminated) else 0.0,
        batch_error=batch_error,
        isam2_error=isam2_error,
        max_difference_mm=difference.raw_mm,
        max_difference_deg=difference.raw_deg,
        aligned_difference_mm=difference.aligned_mm,
        aligned_difference_deg=difference.aligned_deg,
        gauge_m=difference.gauge_m,
        gauge_deg=difference.gauge_deg,
        peer_update_ms=peer_ms,
        ratio=peer_ms / (float(per_event.mean()) * 1e3),
        ate_batch_m=ate_batch,
        ate_isam2_m=ate_isam2,
        factorization=factorization,
        robust_mode=None if robust is None else robust[0],
        robust_seconds=None if robust is None else robust[1],
        robust_outliers=None if robust is None else robust[2],
    )


def _g2o_factors(graph: G2oGraph) -> list[gtsam.NonlinearFactor]:
    return [
        gtsam.BetweenFactorPose2(
            int(i), int(j), gtsam.Pose2(*m), gtsam.noiseModel.Gaussian.Information(info)
        )
        for (i, j), m, info in zip(graph.edges, graph.measurements, graph.information, strict=True)
    ]


def run_g2o_case(
    name: str,
    path: Path,
    relinearize_threshold: float = 0.01,
    relinearize_skip: int = 1,
    factorization: str = "CHOLESKY",
) -> CaseResult:
    """Batch LM over a g2o graph (gauge: a prior on its first vertex, initial values: its
    vertices), and iSAM2 fed one vertex per event with the edges reaching back from it."""
    g = read_g2o(path)
    if not len(g.vertex_ids):
        raise EstimationError(f"{path}: the benchmark needs VERTEX_SE2 lines (initial values)")
    first = int(g.vertex_ids[0])
    gauge = gtsam.PriorFactorPose2(
        first, gtsam.Pose2(*g.poses[0]), gtsam.noiseModel.Isotropic.Sigma(3, _GAUGE_SIGMA)
    )
    factors = _g2o_factors(g)
    full = gtsam.NonlinearFactorGraph()
    full.add(gauge)
    for factor in factors:
        full.add(factor)
    initial = {int(v): p for v, p in zip(g.vertex_ids, g.poses, strict=True)}
    specs = [FactorSpec("prior", (first,), g.poses[0], np.eye(3) * _GAUGE_SIGMA**2, 0)] + [
        FactorSpec("odometry", (int(i), int(j)), m, np.linalg.inv(info), k)
        for k, ((i, j), m, info) in enumerate(
            zip(g.edges, g.measurements, g.information, strict=True)
        )
    ]
    batch = optimize_batch(specs, initial, robust="none")
    batch_seconds = batch.seconds
    batch_estimate = batch.estimate
    result = to_gtsam_values(batch_estimate)

    order = {int(v): n for n, v in enumerate(g.vertex_ids)}
    by_vertex: dict[int, list[int]] = {}
    for k, (i, j) in enumerate(g.edges):
        by_vertex.setdefault(max(order[int(i)], order[int(j)]), []).append(k)
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(relinearize_threshold)
    params.relinearizeSkip = relinearize_skip
    params.setFactorization(factorization)
    isam = gtsam.ISAM2(params)
    in_graph: set[int] = set()
    pending_vertices: list[int] = []
    pending_edges: list[int] = []
    updates: list[float] = []
    overheads: list[float] = []
    updates_cpu: list[float] = []
    overheads_cpu: list[float] = []
    reeliminated: list[int] = []
    counts: list[int] = []
    added = 0
    isam_start = time.perf_counter()
    for n, vertex in enumerate(int(v) for v in g.vertex_ids):
        t0, c0 = time.perf_counter(), time.process_time()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if n == 0:
            graph.add(gauge)
            values.insert(vertex, gtsam.Pose2(*g.poses[0]))
            in_graph.add(vertex)
        else:
            pending_vertices.append(vertex)
            pending_edges += by_vertex.get(n, [])
            # A vertex joins once an edge ties it to the graph; guess it from that edge.
            progress = True
            while progress:
                progress = False
                for k in list(pending_edges):
                    i, j = (int(v) for v in g.edges[k])
                    known, new = (i, j) if i in in_graph else (j, i) if j in in_graph else (0, 0)
                    if known == new or new in in_graph:
                        continue
                    step = gtsam.Pose2(*g.measurements[k])
                    base = (
                        values.atPose2(known)
                        if values.exists(known)
                        else isam.calculateEstimatePose2(known)
                    )
                    values.insert(
                        new, base.compose(step) if known == i else base.compose(step.inverse())
                    )
                    in_graph.add(new)
                    pending_vertices.remove(new)
                    progress = True
            for k in [k for k in pending_edges if {int(v) for v in g.edges[k]} <= in_graph]:
                graph.add(factors[k])
                pending_edges.remove(k)
                added += 1
        t1, c1 = time.perf_counter(), time.process_time()
        again = 0
        if graph.size() or values.size():
            again = int(isam.update(graph, values).getVariablesReeliminated())
        t2, c2 = time.perf_counter(), time.process_time()
        reeliminated.append(again)
        overheads.append(t1 - t0)
        updates.append(t2 - t1)
        overheads_cpu.append(c1 - c0)
        updates_cpu.append(c2 - c1)
        counts.append(added)
    isam2_seconds = time.perf_counter() - isam_start
    isam2_estimate = extract_poses(isam.calculateBestEstimate())
    samples = [counts[int(len(counts) * (i + 1) / _PEER_SAMPLES) - 1] for i in range(_PEER_SAMPLES)]
    order_added = _edge_order(by_vertex)
    prefixes = []
    for count in samples:
        prefix = gtsam.NonlinearFactorGraph()
        prefix.add(gauge)
        for k in order_added[:count]:
            prefix.add(factors[k])
        prefixes.append(prefix)
    return _result(
        name,
        poses=len(g.vertex_ids),
        factors=len(factors) + 1,
        update_seconds=updates,
        python_seconds=overheads,
        update_cpu=updates_cpu,
        python_cpu=overheads_cpu,
        reeliminated=reeliminated,
        isam2_seconds=isam2_seconds,
        batch_seconds=batch_seconds,
        batch_error=float(full.error(result)),
        isam2_error=float(full.error(to_gtsam_values(isam2_estimate))),
        difference=pose_difference(batch_estimate, isam2_estimate),
        peer_ms=_peer_ms(prefixes, batch_estimate),
        factorization=factorization,
    )


def _edge_order(by_vertex: dict[int, list[int]]) -> list[int]:
    """Edges in the order the incremental replay adds them (by their later vertex)."""
    return [k for n in sorted(by_vertex) for k in by_vertex[n]]


def run_bench(
    cases: Sequence[str] = CASES,
    settings: GraphSettings | None = None,
    robust: RobustMode = "gnc_tls",
    relinearize_threshold: float = 0.01,
    relinearize_skip: int = 1,
    data_dir: Path = DATA_DIR,
    progress: Progress | None = None,
) -> dict[str, object]:
    """Run the cases; the JSON object of docs/design.md §11 (top-level figures: the worst case).

    Real-data cases whose file is absent are skipped (listed under ``"skipped"``).
    """
    settings = settings or GraphSettings()
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        raise EstimationError(f"unknown graph bench case {unknown[0]!r}; known: {', '.join(CASES)}")
    results: list[CaseResult] = []
    skipped: list[str] = []
    for name in cases:
        if progress:
            progress(name)
        if name.startswith("leapfrog"):
            scenario = leapfrog_5000(loops=name.endswith("loops"), settings=settings)
            results.append(
                run_leapfrog_case(
                    name, scenario, settings, robust, relinearize_threshold, relinearize_skip
                )
            )
            continue
        path = data_dir / "pose_graphs_g2o" / f"{name}.g2o"
        if not path.exists():
            skipped.append(name)
            continue
        try:
            results.append(run_g2o_case(name, path, relinearize_threshold, relinearize_skip))
        except RuntimeError:
            # Cholesky gives up on an ill-conditioned increment (ais2klinik: a 1,500-pose chain
            # hanging off one loop closure, 5° per step odometry); QR is slower but copes.
            if progress:
                progress(f"{name} (QR)")
            results.append(run_g2o_case(name, path, relinearize_threshold, relinearize_skip, "QR"))
    if not results:
        raise EstimationError("no graph bench case could run (is ../shared/data there?)")
    report: dict[str, object] = {
        "benchmark": "graph",
        "ratio": min(r.ratio for r in results),
        "batch_seconds": max(r.batch_seconds for r in results),
        "isam2_update_median_ms": max(r.isam2_update_median_ms for r in results),
        "isam2_update_p99_ms": max(r.isam2_update_p99_ms for r in results),
        "poses": max(r.poses for r in results),
        "relinearize_threshold": relinearize_threshold,
        "relinearize_skip": relinearize_skip,
        "cases": [asdict(r) for r in results],
    }
    if skipped:
        report["skipped"] = skipped
    return report


def format_report(report: dict[str, object]) -> str:
    """The human-readable table of :func:`run_bench`'s report."""
    cases = report["cases"]
    assert isinstance(cases, list)
    lines = [
        f"coopmap bench graph: batch LM/GNC and iSAM2 (relinearize threshold "
        f"{report['relinearize_threshold']}, skip {report['relinearize_skip']}); iSAM2 per event, "
        "wall clock (CPU time in brackets)",
        f"{'case':20s} {'poses':>6s} {'batch s':>7s} {'iSAM2 s':>7s} {'median ms':>9s} "
        f"{'p99 ms':>13s} {'max ms':>7s} {'py ms':>5s} {'event p99':>13s} {'peer ms':>8s} "
        f"{'ratio':>6s} {'|Δ| raw':>15s} {'|Δ| aligned':>15s} {'error batch/iSAM2':>17s} "
        f"{'ATE m':>6s}",
    ]
    for c in cases:
        ate_text = "-" if c["ate_batch_m"] is None else f"{c['ate_batch_m']:.3f}"
        p99 = f"{c['isam2_update_p99_ms']:.2f} ({c['isam2_update_cpu_p99_ms']:.2f})"
        event = f"{c['event_p99_ms']:.2f} ({c['event_cpu_p99_ms']:.2f})"
        errors = f"{c['batch_error']:.1f}/{c['isam2_error']:.1f}"
        raw = f"{c['max_difference_mm']:.3g} mm {c['max_difference_deg']:.2g}°"
        aligned = f"{c['aligned_difference_mm']:.3g} mm {c['aligned_difference_deg']:.2g}°"
        lines.append(
            f"{c['name']:20s} {c['poses']:6d} {c['batch_seconds']:7.2f} {c['isam2_seconds']:7.1f} "
            f"{c['isam2_update_median_ms']:9.2f} {p99:>13s} {c['isam2_update_max_ms']:7.1f} "
            f"{c['python_overhead_median_ms']:5.2f} {event:>13s} {c['peer_update_ms']:8.1f} "
            f"{c['ratio']:6.1f} {raw:>15s} {aligned:>15s} {errors:>17s} {ate_text:>6s}"
            + ("" if c["factorization"] == "CHOLESKY" else f"  (iSAM2 {c['factorization']})")
        )
    lines.append(
        "variables iSAM2 eliminated again per event (median / p99): "
        + ", ".join(
            f"{c['name']} {c['reeliminated_median']:.0f} / {c['reeliminated_p99']:.0f}"
            for c in cases
        )
    )
    for c in cases:
        if c["robust_mode"] is not None:
            lines.append(
                f"{c['name']}: batch with {c['robust_mode']}: {c['robust_seconds']:.2f} s, "
                f"{c['robust_outliers']} factors rejected"
            )
    if report.get("skipped"):
        lines.append(f"skipped (data absent): {', '.join(report['skipped'])}")  # type: ignore[arg-type]
    lines.append(
        "py ms: Python per event (builder, GTSAM objects); event p99: update + Python; peer: batch "
        "LM re-solve per event, warm-started; ratio: peer / iSAM2 per event\n"
        "|Δ| raw: the largest batch − iSAM2 pose difference as estimated, each in its own gauge; "
        "|Δ| aligned: after the SE(2) transform that best maps iSAM2's positions onto batch's "
        "(the gauge: "
        + ", ".join(f"{c['name']} {c['gauge_m']:.3g} m {c['gauge_deg']:.2g}°" for c in cases)
        + ")"
    )
    return "\n".join(lines)
