"""Exhaustive (x, y, θ) search of a local 2D band grid against a global one (docs/design.md §7,
paper §2.2).

``search`` scores every pose of a window, on the lattice and with the metric of ``lattice``, by
the FFT correlations of ``correlate``, and keeps the whole normalised PDF and its refined,
dominance-checked peak (``peak``); ``windowed_search`` grows a square window around a prior
position until the peak is dominant.

**Best pose alone.** ``best_pose`` finds the same lattice argmax without scoring every pose: by
branch and bound over (rotation, translation block), with true upper bounds of each block's
scores (``bnb``), then refines it as ``search`` does.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from estimation.errors import EstimationError
from estimation.posepdf import PosePdf
from estimation.search.bnb import lattice_best
from estimation.search.correlate import Slices, correlate_lattice
from estimation.search.lattice import (
    EDGE,
    Metric,
    check_pair,
    covers_circle,
    lattice_steps,
    pose_lattice,
    yaw_lattice,
)
from estimation.search.peak import (
    best_pose_outside,
    pdf_from_slices,
    peak_covariance,
    refine_peak,
    refine_pose,
)
from mapping.band import Band

#: The most poses ``search`` scores at once (float32 scores: 1 GiB), with the PDF over them.
MAX_PDF_POSES = 2**28

__all__ = [
    "MAX_PDF_POSES",
    "SearchParams",
    "SearchResult",
    "WindowStep",
    "WindowedResult",
    "best_pose",
    "overlap_fraction",
    "result_from_scores",
    "search",
    "windowed_search",
]


@dataclass(frozen=True)
class SearchParams:
    """Parameters of a search. Names follow the ``search`` section of the configuration; angles
    in radians here (degrees in the configuration)."""

    angular_resolution_rad: float = math.radians(1.0)
    free_weight: float = 0.5
    occupied_level: float = 0.1
    beta: float = 0.04
    peak_radius_m: float = 0.5
    peak_radius_rad: float = math.radians(10.0)
    dominance_ratio: float = 2.0
    workers: int = 0  # threads for the FFT loop; 0: one per CPU, at most 4
    score: str = "agreement"  # lattice.SCORES

    def __post_init__(self) -> None:
        for name in ("angular_resolution_rad", "beta", "peak_radius_m", "peak_radius_rad"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise EstimationError(f"search {name} must be a positive number, got {value!r}")
        Metric(self.free_weight, self.occupied_level, self.score)  # validates them
        if not self.dominance_ratio >= 1:
            raise EstimationError(
                f"search dominance_ratio must be >= 1, got {self.dominance_ratio!r}"
            )
        if self.workers < 0:
            raise EstimationError(f"search workers must be >= 0, got {self.workers}")

    @property
    def metric(self) -> Metric:
        return Metric(self.free_weight, self.occupied_level, self.score)

    def thread_count(self) -> int:
        return self.workers or min(4, os.cpu_count() or 1)


def overlap_fraction(local: Band, global_: Band, pose: np.ndarray) -> float:
    """The share of the local grid's known cells that land on a known cell of the global grid
    when the local frame sits at ``pose`` (x_m, y_m, yaw_rad) in the global frame (a cell centre
    belongs to the global cell containing it, as in the score). A score summed over a small
    overlap rests on little of the local map: few cells of structure in common. EstimationError
    on a local grid with no known cell, a non-finite pose or mismatched resolutions."""
    r = check_pair(local, global_)
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (3,) or not np.isfinite(pose).all():
        raise EstimationError(f"overlap pose must be 3 finite numbers, got {pose!r}")
    known = np.asarray(local.known, dtype=bool)
    if not known.any():
        raise EstimationError("the scan grid has no known cell")
    gx, gy = local.cell_centers()
    px, py = gx[known], gy[known]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    col = np.floor((pose[0] + c * px - s * py - global_.lower_xy[0]) / r + EDGE).astype(np.int64)
    row = np.floor((pose[1] + s * px + c * py - global_.lower_xy[1]) / r + EDGE).astype(np.int64)
    rows, cols = global_.shape
    inside = (col >= 0) & (row >= 0) & (col < cols) & (row < rows)
    hits = np.asarray(global_.known, dtype=bool)[row[inside], col[inside]]
    return float(hits.sum()) / float(known.sum())


# -- the search --------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SearchResult:
    """The exhaustive search's answer: pose of the local grid's frame in the global grid's frame.

    ``prob`` (float32, (T, Y, X) over ``yaw_rad`` × ``y_m`` × ``x_m``) ∝ exp(β·score) sums to
    1; ``scores`` are the float32 scores when the search was asked to keep them (else None: the
    PDF is computed over them). ``pose`` is the refined best pose (x_m, y_m, yaw_rad);
    ``covariance`` (m, m, rad) and ``peak_ratio`` are those of ``pdf`` (``PosePdf``'s
    definitions), computed on the scores.
    """

    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    scores: np.ndarray | None
    prob: np.ndarray
    beta: float
    best_index: tuple[int, int, int]
    best_score: float
    pose: np.ndarray
    covariance: np.ndarray
    peak_ratio: float
    seconds: float

    @cached_property
    def pdf(self) -> PosePdf:
        """The whole normalised PDF as a ``PosePdf`` (a copy of ``prob``, built on first use)."""
        return PosePdf(self.x_m, self.y_m, self.yaw_rad, self.prob)

    @property
    def poses(self) -> int:
        """The number of poses scored."""
        return int(self.prob.size)

    @property
    def lattice_pose(self) -> np.ndarray:
        t, y, x = self.best_index
        return np.array([self.x_m[x], self.y_m[y], self.yaw_rad[t]])

    def is_dominant(self, dominance_ratio: float) -> bool:
        return self.peak_ratio >= dominance_ratio

    def dominant_given(
        self, predicted: np.ndarray, covariance: np.ndarray, params: SearchParams
    ) -> bool:
        """Whether the peak is still the dominant one once each pose is weighed by a Gaussian
        prediction of it: ``predicted`` (x, y, yaw) with ``covariance`` (3, 3) in its tangent
        space (a graph's relative pose). The best pose of P(T)·N(T; predicted, covariance)
        must lie in this search's peak (``params``' peak radii) and stand out by
        ``params.dominance_ratio``. A room that repeats itself (a hall's trusses every
        3.65 m along a plain wall) gives the scores modes one period apart that only chance
        tells apart; the prediction tells them apart, and a peak it finds unlikely beside
        another mode is no measurement to take."""
        predicted = np.asarray(predicted, dtype=np.float64)
        covariance = np.asarray(covariance, dtype=np.float64)
        if predicted.shape != (3,) or covariance.shape != (3, 3):
            raise EstimationError("a prediction is a pose (3,) with a 3x3 covariance")
        if not (np.isfinite(predicted).all() and np.isfinite(covariance).all()):
            raise EstimationError("a prediction must be finite")
        steps = np.array(lattice_steps(self.x_m, self.y_m, self.yaw_rad))
        # A cell's own spread keeps a (near) singular prediction usable.
        information = np.linalg.inv(0.5 * (covariance + covariance.T) + np.diag(steps**2))
        c, s = math.cos(predicted[2]), math.sin(predicted[2])
        dx = (self.x_m - predicted[0])[None, :]
        dy = (self.y_m - predicted[1])[:, None]
        u, v = c * dx + s * dy, c * dy - s * dx  # (Y, X), in the predicted pose's axes
        planar = information[0, 0] * u**2 + 2 * information[0, 1] * u * v + information[1, 1] * v**2
        turns = np.remainder(self.yaw_rad - predicted[2] + math.pi, 2 * math.pi) - math.pi
        # log P(T) − ½ d²(T) one rotation at a time: a loop closure's window holds millions of
        # poses, and whole-lattice temporaries cost more memory than the search itself.
        weighed = np.empty(np.shape(self.prob), dtype=np.float32)
        with np.errstate(divide="ignore"):
            for t, w in enumerate(turns):
                squared = planar + w * (2 * information[0, 2] * u + 2 * information[1, 2] * v
                                        + information[2, 2] * w)  # fmt: skip
                weighed[t] = np.log(np.asarray(self.prob[t], dtype=np.float64)) - 0.5 * squared
        best = np.unravel_index(int(np.argmax(weighed)), weighed.shape)
        top = float(weighed[best])
        if not math.isfinite(top):
            return False
        bt, by, bx = (int(i) for i in best)
        own = self.lattice_pose
        if (
            math.hypot(self.x_m[bx] - own[0], self.y_m[by] - own[1]) > params.peak_radius_m + 1e-9
            or abs(math.remainder(self.yaw_rad[bt] - own[2], 2 * math.pi))
            > params.peak_radius_rad + 1e-9
        ):
            return False  # the prediction prefers another mode
        # The best weighed pose outside the peak's neighbourhood (PosePdf.peak_ratio's).
        near_xy = np.hypot(self.x_m[None, :] - self.x_m[bx], self.y_m[:, None] - self.y_m[by])
        near_xy = near_xy <= params.peak_radius_m + 1e-12
        apart = np.abs(np.remainder(self.yaw_rad - self.yaw_rad[bt] + math.pi, 2 * math.pi)
                       - math.pi)  # fmt: skip
        elsewhere = -math.inf
        for t in range(len(self.yaw_rad)):
            far = apart[t] > params.peak_radius_rad + 1e-12
            slice_ = weighed[t] if far else weighed[t][~near_xy]
            if slice_.size:
                elsewhere = max(elsewhere, float(slice_.max()))
        return top - elsewhere >= math.log(params.dominance_ratio)

    def modes(self, count: int, radius_m: float, radius_rad: float) -> list[np.ndarray]:
        """Up to ``count`` poses (x, y, yaw): the refined best pose, then the most probable
        lattice poses each farther than ``radius_m`` or ``radius_rad`` from every one before
        it (the PDF's other modes, most probable first; none below 1e-12 of the best)."""
        prob = np.asarray(self.prob)
        t, y, x = self.best_index
        chosen = [np.asarray(self.pose, dtype=float)]
        taken = [(self.x_m[x], self.y_m[y], self.yaw_rad[t])]
        floor = 1e-12 * float(prob[t, y, x])
        # Candidates: the best pose of each yaw slice and position, most probable first.
        flat = prob.max(axis=0)
        yaw_of = prob.argmax(axis=0)
        order = np.argsort(flat, axis=None)[::-1]
        for index in order:
            if len(chosen) >= count or flat.flat[index] <= floor:
                break
            iy, ix = np.unravel_index(int(index), flat.shape)
            pose = (self.x_m[ix], self.y_m[iy], self.yaw_rad[yaw_of[iy, ix]])
            if all(
                math.hypot(pose[0] - q[0], pose[1] - q[1]) > radius_m
                or abs(math.remainder(pose[2] - q[2], 2 * math.pi)) > radius_rad
                for q in taken
            ):
                taken.append(pose)
                chosen.append(np.array(pose, dtype=float))
        return chosen

    def position_marginal(self) -> np.ndarray:
        """(Y, X) float64: the probability of each position, summed over rotations."""
        return np.asarray(self.prob.sum(axis=0, dtype=np.float64))


def result_from_scores(
    scores: np.ndarray,
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    params: SearchParams,
    started: float,
    grids: tuple[Band, Band] | None = None,
    slices: Slices | None = None,
    keep_scores: bool = True,
) -> SearchResult:
    """Best pose, refinement, PDF, covariance and dominance of a score lattice (T, Y, X).

    The best lattice pose is refined by a quadratic fitted to the scores around it, then, when
    the (local, global) ``grids`` are given, by maximising the spline-interpolated score
    within two lattice steps of it (``refine_pose``): near-flat peaks can put the best lattice
    cell a step away from the one nearest the optimum. Without ``keep_scores`` the PDF is
    computed over the scores (float32, contiguous), which are then gone.
    """
    scores = np.ascontiguousarray(scores, dtype=np.float32)
    if slices is None or slices.beta != params.beta:
        slices = Slices(params.beta, np.empty(len(scores)), np.zeros(len(scores)))
        scratch = np.empty(scores.shape[1:], dtype=np.float32)
        for i in range(len(scores)):
            slices.record(i, scores[i], scratch)
    maxima = slices.maxima
    t = int(np.argmax(maxima))
    y, x = (int(i) for i in np.unravel_index(int(np.argmax(scores[t])), scores.shape[1:]))
    best = float(scores[t, y, x])
    delta = refine_peak(scores, (t, y, x), covers_circle(yaw_rad))
    steps = np.array(lattice_steps(x_m, y_m, yaw_rad))
    lattice = np.array([x_m[x], y_m[y], yaw_rad[t]])
    pose = lattice + delta * steps
    if grids is not None:
        bounds = np.column_stack([lattice - 2 * steps, lattice + 2 * steps])
        pose = refine_pose(grids[0], grids[1], pose, params.metric, bounds)
    pose[2] = float((pose[2] + math.pi) % (2.0 * math.pi) - math.pi)
    radii = (params.peak_radius_m, params.peak_radius_rad)
    elsewhere = best_pose_outside(scores, (t, y, x), x_m, y_m, yaw_rad, *radii, maxima=maxima)
    with np.errstate(over="ignore"):
        ratio = float(np.exp(params.beta * (best - elsewhere)))
    covariance = peak_covariance(scores, (t, y, x), x_m, y_m, yaw_rad, params.beta, *radii)
    prob = pdf_from_slices(scores, slices, params.thread_count(), in_place=not keep_scores)
    return SearchResult(
        x_m=x_m,
        y_m=y_m,
        yaw_rad=yaw_rad,
        scores=scores if keep_scores else None,
        prob=prob,
        beta=params.beta,
        best_index=(t, y, x),
        best_score=best,
        pose=pose,
        covariance=covariance,
        peak_ratio=ratio,
        seconds=time.perf_counter() - started,
    )


def search(
    local: Band,
    global_: Band,
    params: SearchParams,
    window_m: tuple[float, float, float, float] | None = None,
    *,
    keep_scores: bool = False,
) -> SearchResult:
    """Score every pose (x, y, θ) of the window (default: the whole global grid) at the grids'
    resolution and ``params.angular_resolution_rad``; the whole normalised PDF and its peak.
    The scores are kept in the result only when asked (the PDF is otherwise computed over
    them, in place).

    The pose is that of ``local``'s frame (the frame its ``lower_xy`` is given in) in
    ``global_``'s frame. EstimationError on an empty scan or map, mismatched resolutions or a
    window outside the map.
    """
    started = time.perf_counter()
    x_m, y_m, _ = pose_lattice(local, global_, window_m)
    yaw_rad = yaw_lattice(params.angular_resolution_rad)
    poses = len(x_m) * len(y_m) * len(yaw_rad)
    if poses > MAX_PDF_POSES:
        raise EstimationError(
            f"the whole-PDF search would score {poses:,} poses ({len(x_m)} × {len(y_m)} "
            f"positions × {len(yaw_rad)} headings, {4 * poses / 2**30:.1f} GiB); at most "
            f"{MAX_PDF_POSES:,} are scored at once: search a window around a prior, or a "
            "coarser grid or angular resolution"
        )
    scores, slices = correlate_lattice(
        local, global_, x_m, y_m, yaw_rad, params.metric, params.thread_count(), params.beta
    )
    assert scores is not None
    return result_from_scores(
        scores, x_m, y_m, yaw_rad, params, started, (local, global_), slices, keep_scores
    )


def best_pose(
    local: Band,
    global_: Band,
    params: SearchParams,
    window_m: tuple[float, float, float, float] | None = None,
) -> tuple[np.ndarray, float, float]:
    """The refined best pose alone (x_m, y_m, yaw_rad), its lattice score and the seconds it
    took: the lattice argmax of the exhaustive search (``bnb.lattice_best``: branch and
    bound, exact, without scoring every pose), then ``search``'s refinement — a quadratic over
    the 3×3×3 scores around it, then ``refine_pose``. The ``excess`` score, which the bounds do
    not cover, is searched exhaustively (``search``). EstimationError as ``search``."""
    if params.score == "excess":  # the branch and bound's bounds are of one correlation
        found = search(local, global_, params, window_m)
        return found.pose, found.best_score, found.seconds
    started = time.perf_counter()
    x_m, y_m, _ = pose_lattice(local, global_, window_m)
    yaw_rad = yaw_lattice(params.angular_resolution_rad)
    best = lattice_best(local, global_, x_m, y_m, yaw_rad, params.metric, params.thread_count())
    t, y, x = best.index
    # ``near`` is the neighbourhood refine_peak reads in the full search, cut at the lattice's
    # edges: the best pose sits at its centre unless on an edge.
    index = (len(best.near) // 2, min(y, 1), min(x, 1))
    steps = np.array(lattice_steps(x_m, y_m, yaw_rad))
    lattice = np.array([x_m[x], y_m[y], yaw_rad[t]])
    pose = lattice + refine_peak(best.near, index, yaw_wraps=False) * steps
    bounds = np.column_stack([lattice - 2 * steps, lattice + 2 * steps])
    pose = refine_pose(local, global_, pose, params.metric, bounds)
    pose[2] = float((pose[2] + math.pi) % (2.0 * math.pi) - math.pi)
    return pose, best.score, time.perf_counter() - started


# -- windowed search around an estimate --------------------------------------------------------


@dataclass(frozen=True)
class WindowStep:
    """One window of a windowed search: its side, what it found, and why it did (not) stop."""

    side_m: float
    window_m: tuple[float, float, float, float]
    pose: np.ndarray
    peak_ratio: float
    on_edge: bool  # the best cell lies on a border of the window that is not the map's border
    covers_map: bool
    seconds: float


@dataclass(frozen=True)
class WindowedResult:
    """The last window's search, and every window tried (smallest first)."""

    result: SearchResult
    steps: tuple[WindowStep, ...]
    dominance_ratio: float

    @property
    def dominant(self) -> bool:
        """Whether the search stopped on a dominant peak inside its window."""
        last = self.steps[-1]
        return not last.on_edge and last.peak_ratio >= self.dominance_ratio


def windowed_search(
    local: Band,
    global_: Band,
    params: SearchParams,
    prior_xy: tuple[float, float] | np.ndarray,
    window_m: float,
    max_window_m: float,
) -> WindowedResult:
    """Search a square window of side ``window_m`` centred on the prior position, then windows
    twice as wide, until the peak is dominant (``peak_ratio ≥ params.dominance_ratio``, with the
    best cell off the window's inner borders), the window covers the whole map, or its side
    reaches ``max_window_m``. The batch form of the paper's spiral search out from an estimate:
    every rotation is searched in each window, and the answer is the last window's whole PDF.
    """
    px, py = (float(v) for v in prior_xy)
    if not (math.isfinite(px) and math.isfinite(py)):
        raise EstimationError(f"prior position must be finite, got ({px}, {py})")
    if not (0 < window_m <= max_window_m) or not math.isfinite(max_window_m):
        raise EstimationError(
            f"need 0 < window_m <= max_window_m, got {window_m} and {max_window_m}"
        )
    mx0, mx1, my0, my1 = global_.extent()
    steps: list[WindowStep] = []
    side = float(window_m)
    while True:
        window = (px - side / 2, px + side / 2, py - side / 2, py + side / 2)
        result = search(local, global_, params, window)
        covers = window[0] <= mx0 and window[1] >= mx1 and window[2] <= my0 and window[3] >= my1
        _, by, bx = result.best_index
        r = float(global_.resolution_m)
        inner = (
            (bx == 0 and result.x_m[0] - r >= mx0)
            or (bx == len(result.x_m) - 1 and result.x_m[-1] + r < mx1)
            or (by == 0 and result.y_m[0] - r >= my0)
            or (by == len(result.y_m) - 1 and result.y_m[-1] + r < my1)
        )
        steps.append(
            WindowStep(
                side_m=side,
                window_m=window,
                pose=result.pose,
                peak_ratio=result.peak_ratio,
                on_edge=bool(inner),
                covers_map=bool(covers),
                seconds=result.seconds,
            )
        )
        dominant = result.peak_ratio >= params.dominance_ratio and not inner
        if dominant or covers or side >= max_window_m:
            return WindowedResult(result, tuple(steps), params.dominance_ratio)
        del result  # the next, larger window's PDF must not sit beside this one
        side = min(2.0 * side, float(max_window_m))
