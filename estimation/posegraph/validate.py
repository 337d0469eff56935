"""The validator hook (docs/design.md §5): optimized stations scored against their search PDFs.

Each global-localization result keeps its whole pose PDF. After optimization, a station whose
optimized pose (in the PDF's frame: the map, or the reference station) lies outside the region
holding ``mass`` of the PDF's probability has been pulled away by other factors. To find them,
the most stressed mutual and global factors are each left out in turn and the graph re-solved:
the one whose removal brings the stations back into their regions pulled them, and is flagged.
:func:`validate_and_repair` disables flagged factors and re-optimizes until the stations agree
with their searches (or nothing more is flagged).

A search result whose own factor was rejected as an outlier (by GNC, or disabled) is reported
but flags nothing: then it is the search, not the graph, that is suspect. A search whose factor
carries a registration's refinement instead of the PDF's best pose (docs/design.md §7) is
checked against that factor's own Gaussian: the station lies in its region when the factor's
squared Mahalanobis norm stays below the χ² quantile of ``mass`` (three degrees of freedom).
Its PDF, on the search's lattice, is sharper than the registration and centred a few
centimetres away; checked against it, a station the registration placed well lay outside.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from estimation.chi2 import chi2_cdf, chi2_quantile
from estimation.errors import EstimationError
from estimation.posegraph.graph import FactorSpec
from estimation.posegraph.gtsam_factors import to_gtsam_graph, to_gtsam_values
from estimation.posegraph.keys import key_label
from estimation.posegraph.smoother import BatchResult, RobustMode, extract_poses, optimize_batch
from estimation.posepdf import PosePdf
from sensors.geometry import se2

__all__ = ["StationCheck", "Validation", "validate_and_repair", "validate_stations"]

SearchResults = Mapping[int, Sequence[tuple[PosePdf, int | None]]]


@dataclass(frozen=True)
class StationCheck:
    """One search result checked: the optimized pose in the PDF's frame, the probability of the
    cells more probable than it (0 at the peak), and whether it lies in the region."""

    key: int
    reference: int | None
    pose: np.ndarray
    mass_above: float
    inside: bool
    search_factor_kept: bool

    def describe(self) -> str:
        frame = "map" if self.reference is None else key_label(self.reference)
        verdict = "inside" if self.inside else "OUTSIDE"
        return (
            f"{key_label(self.key)} in {frame}: {verdict} the search region "
            f"(mass above {self.mass_above:.3f})"
        )


@dataclass(frozen=True)
class Validation:
    """All checks, and the indices (into the factor list) of the factors flagged."""

    checks: tuple[StationCheck, ...]
    flagged: tuple[int, ...]

    @property
    def failed(self) -> list[StationCheck]:
        return [c for c in self.checks if not c.inside]

    @property
    def ok(self) -> bool:
        return not self.failed


def _search_factor(
    factors: Sequence[FactorSpec], active: np.ndarray, key: int, reference: int | None, pdf: PosePdf
) -> FactorSpec | None:
    """The active global factor that carries this search result: same keys, and the PDF's best
    pose as its mean or, refined by a registration, the nearest such factor to it (within the
    PDF's window). None when no active factor carries it."""
    keys = (key,) if reference is None else (reference, key)
    best = pdf.best_pose()
    found: tuple[float, FactorSpec] | None = None
    for i, f in enumerate(factors):
        if not (active[i] and f.kind == "global" and f.keys == keys):
            continue
        if np.allclose(f.measurement, best):
            return f
        if pdf.nearest_index(np.asarray(f.measurement, dtype=float)) is None:
            continue
        distance = math.dist(f.measurement[:2], best[:2])
        if found is None or distance < found[0]:
            found = (distance, f)
    return None if found is None else found[1]


def _solve_without(
    factors: Sequence[FactorSpec],
    active: np.ndarray,
    estimate: Mapping[int, np.ndarray],
    left_out: int,
) -> dict[int, np.ndarray] | None:
    """The active graph re-solved without one factor, from ``estimate`` (None if that leaves a
    pose unconstrained)."""
    graph = to_gtsam_graph([f for i, f in enumerate(factors) if active[i] and i != left_out])
    try:
        result = gtsam.LevenbergMarquardtOptimizer(graph, to_gtsam_values(estimate)).optimize()
    except RuntimeError:
        return None
    return extract_poses(result)


def _check(
    estimate: Mapping[int, np.ndarray],
    key: int,
    reference: int | None,
    pdf: PosePdf,
    mass: float,
    factor: FactorSpec | None,
) -> StationCheck:
    """The check of one search result; against its factor's Gaussian when the factor carries a
    registration's refinement (its mean is not the PDF's best pose)."""
    base = np.zeros(3) if reference is None else estimate[reference]
    pose = se2.between(base, estimate[key])
    if factor is not None and not np.allclose(factor.measurement, pdf.best_pose()):
        m2 = factor.mahalanobis2(estimate)
        return StationCheck(
            key=key,
            reference=reference,
            pose=pose,
            mass_above=chi2_cdf(m2, 3),
            inside=m2 <= chi2_quantile(mass, 3),
            search_factor_kept=True,
        )
    return StationCheck(
        key=key,
        reference=reference,
        pose=pose,
        mass_above=pdf.mass_above(pose),
        inside=pdf.contains(pose, mass),
        search_factor_kept=factor is not None,
    )


def validate_stations(
    estimate: Mapping[int, np.ndarray],
    factors: Sequence[FactorSpec],
    searches: SearchResults,
    mass: float = 0.99,
    active: np.ndarray | None = None,
    max_candidates: int = 10,
) -> Validation:
    """Score every search result against ``estimate`` and flag the factor that pulled stations
    out of their regions. ``active`` marks the factors the estimate used (default: all).

    Suspects are the active mutual and global factors under the most stress (χ² at the
    estimate above its 90 % quantile), at most ``max_candidates``, most stressed first. Each is
    left out in turn and the graph re-solved: the one whose removal brings the most failed
    stations back inside their regions (ties: less probability mass above them) is flagged. One
    factor per call — :func:`validate_and_repair` repeats after disabling it, since one wrong
    factor typically drags many stations along.
    """
    active = np.ones(len(factors), dtype=bool) if active is None else np.asarray(active, bool)
    if len(active) != len(factors):
        raise EstimationError(f"validator: {len(active)} flags for {len(factors)} factors")
    results: list[tuple[int, int | None, PosePdf, FactorSpec | None]] = []
    checks: list[StationCheck] = []
    for key, station_results in searches.items():
        for pdf, reference in station_results:
            for k in (key, reference):
                if k is not None and k not in estimate:
                    raise EstimationError(f"validator: {key_label(k)} is not in the estimate")
            factor = _search_factor(factors, active, key, reference, pdf)
            checks.append(_check(estimate, key, reference, pdf, mass, factor))
            results.append((key, reference, pdf, factor))
    failing = [i for i, c in enumerate(checks) if not c.inside and c.search_factor_kept]
    if not failing:
        return Validation(checks=tuple(checks), flagged=())
    stress = chi2_quantile(0.9, 3)
    scored = [
        (spec.mahalanobis2(estimate), i)
        for i, spec in enumerate(factors)
        if active[i] and spec.robust
    ]
    suspects = [i for m2, i in sorted(scored, reverse=True) if m2 > stress][:max_candidates]
    best: tuple[int, float, int] | None = None  # (stations fixed, −mass above, factor)
    for i in suspects:
        solution = _solve_without(factors, active, estimate, i)
        if solution is None:
            continue
        after = [
            _check(solution, key, ref, pdf, mass, factor)
            for key, ref, pdf, factor in (results[j] for j in failing)
        ]
        score = (sum(c.inside for c in after), -sum(c.mass_above for c in after), i)
        if score[0] > 0 and (best is None or score[:2] > best[:2]):
            best = (score[0], score[1], i)
    flagged = () if best is None else (best[2],)
    return Validation(checks=tuple(checks), flagged=flagged)


def validate_and_repair(
    factors: Sequence[FactorSpec],
    initial: Mapping[int, np.ndarray],
    searches: SearchResults,
    mass: float = 0.99,
    robust: RobustMode = "gnc_tls",
    max_rounds: int = 3,
) -> tuple[BatchResult, list[Validation], np.ndarray]:
    """Optimize, validate, disable the flagged factors and re-optimize, up to ``max_rounds``.

    Returns the last result, the validation of every round, and the mask of factors still
    enabled (disabled factors are left out of the result's ``inliers`` too).
    """
    enabled = np.ones(len(factors), dtype=bool)
    rounds: list[Validation] = []
    while True:
        index = np.flatnonzero(enabled)
        result = optimize_batch([factors[int(i)] for i in index], initial, robust=robust)
        used = np.zeros(len(factors), dtype=bool)
        used[index[result.inliers]] = True
        validation = validate_stations(result.estimate, factors, searches, mass, active=used)
        rounds.append(validation)
        if not validation.flagged or len(rounds) > max_rounds:
            break
        enabled[list(validation.flagged)] = False
    full = BatchResult(
        estimate=result.estimate,
        inliers=used,
        error=result.error,
        seconds=result.seconds,
        covariances=result.covariances,
    )
    return full, rounds, enabled
