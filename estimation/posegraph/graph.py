"""The pose graph (docs/design.md §5): events in, factors and initial values out.

:class:`GraphBuilder` turns the event stream (``estimation.posegraph.events``) into factor
specifications and initial values, one :class:`Increment` per event. The batch smoother collects
them all; iSAM2 is fed each increment as it comes — the same builder for both, so both solve the
same problem.

Variables are the robot poses ``T_map_robot`` (keys from ``estimation.posegraph.keys``). Factors:

* ``prior`` — the gauge on the first reference pose (:class:`~estimation.posegraph.events.Start`);
* ``odometry`` — ``BetweenFactorPose2`` between consecutive poses of one robot, with sigmas
  growing with the distance and angle travelled;
* ``mutual`` — one ``BetweenFactorPose2`` per mutual observation: the maximum-likelihood relative
  pose of the two robots from the four raw beacon measurements (``estimation.posegraph.mutual``),
  with its covariance, the Cramér–Rao bound. To first order this carries exactly the information of
  the raw range/bearing factors, in one native factor without beacon variables (``factor_study``
  measures the alternatives);
* ``global`` — a search result: a prior in the map frame, or a between-factor to the earlier
  station whose map was matched; mean and covariance from the search PDF's peak, floored.

In front of the graph every observation passes the gate: degenerate geometry, the s1/s2
consistency check (paper §2.1) and, when the two robots were related by earlier accepted
observations, a χ² test against the relative pose predicted from them and the odometry since
(the pair's own last fix, or a chain through a third robot's, whichever is tightest).

Covariances of Pose2 factors are in GTSAM's tangent space (body frame, ``[v_x, v_y, ω]``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from estimation.chi2 import chi2_quantile
from estimation.errors import EstimationError
from estimation.posegraph.events import Event, Localize, Move, Observe, Start, checked_covariance
from estimation.posegraph.keys import check_robot, key_label, pose_key, split_key
from estimation.posegraph.mutual import GAP_OUTLIER, check_observation, gap_scale, localize_mutual
from estimation.posegraph.seed import seed_pose
from estimation.posepdf import PosePdf
from sensors.geometry import se2

__all__ = [
    "FactorKind",
    "FactorSpec",
    "GraphBuilder",
    "GraphSettings",
    "Increment",
    "Rejection",
    "floor_covariance",
    "frame_to_body_covariance",
    "mutual_between",
    "odometry_covariance",
]

FactorKind = Literal["prior", "odometry", "mutual", "global"]
RobustKernel = Literal["none", "huber", "cauchy"]


@dataclass(frozen=True)
class GraphSettings:
    """Explicit noise models and gates of the pose graph (SI units; defaults = configs/default).

    ``prediction_gate_probability`` None switches the prediction gate off.
    ``mutual_scale_min``: the mutual observations' covariance is scaled by the spread of the
    s1 − s2 gaps accepted so far (:meth:`GraphBuilder.mutual_scale`), down to this factor of
    the standard deviations; None keeps the configured noise as it is.
    """

    prior_sigma_m: float = 0.001
    prior_sigma_rad: float = math.radians(0.01)
    odometry_sigma_m: float = 0.01
    odometry_sigma_per_m: float = 0.05
    odometry_sigma_rad: float = math.radians(0.5)
    odometry_sigma_rad_per_rad: float = math.radians(2.0)
    range_sigma_m: float = 0.02
    bearing_sigma_rad: float = math.radians(0.25)
    beacon_offset_m: float = 0.25
    scanner_x_m: float = 0.10
    global_min_sigma_m: float = 0.02
    global_min_sigma_rad: float = math.radians(0.3)
    gate_sigmas: float = 3.0
    prediction_gate_probability: float | None = 0.999
    dominance_ratio: float = 2.0
    peak_radius_m: float = 0.5
    peak_radius_rad: float = math.radians(10.0)
    mutual_scale_min: float | None = 0.1

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if value is None:
                continue
            positive_or_zero = name in ("odometry_sigma_per_m", "odometry_sigma_rad_per_rad")
            if not math.isfinite(value) or value < 0 or (value == 0 and not positive_or_zero):
                raise EstimationError(f"GraphSettings.{name} must be positive, got {value}")
        if self.mutual_scale_min is not None and self.mutual_scale_min > 1:
            raise EstimationError(
                f"GraphSettings.mutual_scale_min must be at most 1: {self.mutual_scale_min}"
            )
        p = self.prediction_gate_probability
        if p is not None and not 0 < p < 1:
            raise EstimationError(
                f"GraphSettings.prediction_gate_probability must be in (0, 1): {p}"
            )

    @property
    def prior_covariance(self) -> np.ndarray:
        return np.diag([self.prior_sigma_m**2, self.prior_sigma_m**2, self.prior_sigma_rad**2])


@dataclass(frozen=True, eq=False)
class FactorSpec:
    """One factor, independent of GTSAM: ``measurement`` is the prior pose (one key) or the
    relative pose T_k0_k1 (two keys); ``covariance`` is in the measurement's tangent space."""

    kind: FactorKind
    keys: tuple[int, ...]
    measurement: np.ndarray
    covariance: np.ndarray
    event: int

    @property
    def robust(self) -> bool:
        """Mutual and global factors may be outliers; priors and odometry are known inliers."""
        return self.kind in ("mutual", "global")

    def describe(self) -> str:
        return f"{self.kind} {'-'.join(key_label(k) for k in self.keys)} (event {self.event})"

    def residual(self, poses: Mapping[int, np.ndarray]) -> np.ndarray:
        """Residual (3,) at ``poses`` in GTSAM's Pose2 chart: ``Log(measurement⁻¹ ∘ predicted)``."""
        predicted = (
            poses[self.keys[0]]
            if len(self.keys) == 1
            else se2.between(poses[self.keys[0]], poses[self.keys[1]])
        )
        return se2.log(se2.between(self.measurement, predicted))

    def mahalanobis2(self, poses: Mapping[int, np.ndarray]) -> float:
        """Squared Mahalanobis norm of the residual (twice GTSAM's ``factor.error``)."""
        r = self.residual(poses)
        return float(r @ np.linalg.solve(self.covariance, r))


@dataclass(frozen=True)
class Rejection:
    """An event the gate kept out of the graph, and why; for a mutual observation, the poses it
    joined and the relative pose it measured (None where the geometry gave none)."""

    event: int
    reason: str
    keys: tuple[int, ...] = ()
    measurement: np.ndarray | None = None


@dataclass(frozen=True)
class Increment:
    """What one event adds: factors, initial values of new poses, or a rejection."""

    event: int
    factors: tuple[FactorSpec, ...] = ()
    values: Mapping[int, np.ndarray] = field(default_factory=dict)
    rejection: Rejection | None = None


def odometry_covariance(
    delta: np.ndarray,
    sigma_m: float,
    sigma_per_m: float,
    sigma_rad: float,
    sigma_rad_per_rad: float,
    motion: tuple[float, float] | None = None,
) -> np.ndarray:
    """Diagonal covariance of one odometry step: sigmas grow with the distance driven and the
    angle turned — along the way (``motion``: m, rad) when known, else of the net ``delta``."""
    dx, dy, dyaw = (float(v) for v in delta)
    if motion is None:
        motion = (math.hypot(dx, dy), abs(float(se2.wrap_angle(dyaw))))
    s_t = sigma_m + sigma_per_m * motion[0]
    s_r = sigma_rad + sigma_rad_per_rad * motion[1]
    return np.diag([s_t**2, s_t**2, s_r**2])


def frame_to_body_covariance(yaw_rad: float, covariance: np.ndarray) -> np.ndarray:
    """A covariance of (x, y, yaw) in the parent frame, expressed in the pose's tangent space."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    J = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.asarray(J @ covariance @ J.T)


def floor_covariance(
    covariance: np.ndarray, min_sigma_m: float, min_sigma_rad: float
) -> np.ndarray:
    """Raise the diagonal to at least the floor variances (adds only: stays positive definite)."""
    floor = np.array([min_sigma_m**2, min_sigma_m**2, min_sigma_rad**2])
    return np.asarray(covariance + np.diag(np.maximum(floor - np.diag(covariance), 0.0)))


def mutual_between(
    pose_scanner: np.ndarray, covariance_scanner: np.ndarray, scanner_x_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """T_robotA_robotC and its tangent-space covariance from C's scanner pose in A's scanner frame
    (covariance in A-frame x, y, yaw); the scanner sits ``scanner_x_m`` ahead of the robot origin.

    ``T_rA_rC = T_r_s ∘ T_sA_sC ∘ T_s_r``; a right perturbation ξ of ``T_sA_sC`` becomes
    ``Ad(T_r_s) ξ`` of ``T_rA_rC``.
    """
    T_r_s = np.array([scanner_x_m, 0.0, 0.0])
    body = frame_to_body_covariance(float(pose_scanner[2]), covariance_scanner)
    T = se2.compose(se2.compose(T_r_s, pose_scanner), se2.inverse(T_r_s))
    Ad = se2.adjoint(T_r_s)
    cov = Ad @ body @ Ad.T
    return T, 0.5 * (cov + cov.T)


def _inverse_with_covariance(T: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Ad = se2.adjoint(T)
    return se2.inverse(T), Ad @ cov @ Ad.T


@dataclass
class _Step:
    previous: int
    delta: np.ndarray
    covariance: np.ndarray


class GraphBuilder:
    """Turns events into :class:`Increment` s; keeps what the gate and the seeds need.

    State: known poses and their initial guesses, each robot's odometry steps, the last accepted
    relative pose of every pair of robots, the search PDFs of the stations, the rejections.
    """

    def __init__(self, settings: GraphSettings | None = None) -> None:
        self.settings = settings or GraphSettings()
        self.factors: list[FactorSpec] = []
        self.guesses: dict[int, np.ndarray] = {}
        self.rejections: list[Rejection] = []
        self.pdfs: dict[int, list[tuple[PosePdf, int | None]]] = {}
        self._sources: dict[int, str] = {}
        self._anchors: dict[str, int] = {}
        self._seed_chi2 = chi2_quantile(0.999, 3)
        self._latest: dict[str, int] = {}
        self._steps: dict[str, dict[int, _Step]] = {}
        self._fixes: dict[tuple[str, str], tuple[int, int, np.ndarray, np.ndarray]] = {}
        self._gaps: list[float] = []  # |s1 - s2| / its predicted deviation, accepted so far
        self._events = 0
        s = self.settings
        self._gate_chi2 = (
            chi2_quantile(s.prediction_gate_probability, 3)
            if s.prediction_gate_probability is not None
            else math.inf
        )

    # -- public ----------------------------------------------------------------------------

    @property
    def events(self) -> int:
        """Events consumed so far."""
        return self._events

    def mutual_scale(self) -> float:
        """The factor on the standard deviations of the next mutual observation's factor
        (:func:`~estimation.posegraph.mutual.gap_scale` of the gaps accepted so far). It
        depends only on the events before, in order: the mission loop and ``batch`` on its
        recording weigh every observation alike. An observation whose gap exceeds
        ``GAP_OUTLIER`` times it is rejected (a false detection that the configured s1/s2 gate
        let through would otherwise enter with the clean observations' small covariance)."""
        return gap_scale(self._gaps, self.settings.mutual_scale_min)

    def initial_values(self) -> dict[int, np.ndarray]:
        """The current guess of every pose (batch initial values; seeds applied)."""
        return {k: v.copy() for k, v in self.guesses.items()}

    def add(self, event: Event) -> Increment:
        """Consume one event; raises ``EstimationError`` when the stream is inconsistent."""
        number = self._events
        if isinstance(event, Start):
            increment = self._start(event, number)
        elif isinstance(event, Move):
            increment = self._move(event, number)
        elif isinstance(event, Observe):
            increment = self._observe(event, number)
        elif isinstance(event, Localize):
            increment = self._localize(event, number)
        else:
            raise EstimationError(f"event {number}: unknown event type {type(event).__name__}")
        self._events += 1
        self.factors.extend(increment.factors)
        if increment.rejection is not None:
            self.rejections.append(increment.rejection)
        return increment

    def add_all(self, events: Iterable[Event]) -> list[Increment]:
        return [self.add(e) for e in events]

    # -- events ----------------------------------------------------------------------------

    def _new_pose(self, key: int, guess: np.ndarray, source: str) -> dict[int, np.ndarray]:
        self.guesses[key] = np.asarray(guess, dtype=float).copy()
        self._sources[key] = source
        robot, index = split_key(key)
        self._latest[robot] = max(self._latest.get(robot, index), index)
        if source != "move":
            self._anchors[robot] = index
        return {key: self.guesses[key].copy()}

    def _refine_guess(
        self, key: int, guess: np.ndarray, covariance: np.ndarray, source: str
    ) -> None:
        """Replace an odometry-only guess by one from an observation or a search, if the two
        agree within the dead-reckoning uncertainty since the robot's last anchored pose (χ² at
        0.999). A gross outlier, even one let into the graph, must not drag the initial values
        of every pose after it."""
        if self._sources[key] != "move":
            return
        robot, index = split_key(key)
        anchor = self._anchors.get(robot)
        motion = None if anchor is None else self._motion(robot, anchor, index)
        if motion is None:
            return
        xi = se2.log(se2.between(self.guesses[key], guess))
        if float(xi @ np.linalg.solve(motion[1] + covariance, xi)) > self._seed_chi2:
            return
        self.guesses[key] = np.asarray(guess, dtype=float).copy()
        self._sources[key] = source
        self._anchors[robot] = index

    def _start(self, event: Start, number: int) -> Increment:
        key = pose_key(event.robot, event.index)
        pose = np.asarray(event.pose, dtype=float)
        _finite(number, "Start.pose", pose)
        values = {} if key in self.guesses else self._new_pose(key, pose, "start")
        spec = FactorSpec("prior", (key,), pose, self.settings.prior_covariance, number)
        return Increment(number, (spec,), values)

    def _move(self, event: Move, number: int) -> Increment:
        robot = check_robot(event.robot)
        delta = np.asarray(event.delta, dtype=float)
        _finite(number, "Move.delta", delta)
        if event.motion is not None and not (
            len(event.motion) == 2 and all(math.isfinite(v) and v >= 0 for v in event.motion)
        ):
            raise EstimationError(
                f"event {number}: Move.motion (m driven, rad turned) must be two finite numbers "
                f">= 0, got {event.motion}"
            )
        if robot not in self._latest:
            raise EstimationError(
                f"event {number}: robot {robot!r} moves but has no pose yet (its first pose comes "
                "from a Start, Observe or Localize event)"
            )
        previous = self._latest[robot]
        if event.index <= previous:
            raise EstimationError(
                f"event {number}: robot {robot!r} moves to pose {event.index}, not after its "
                f"latest pose {previous}"
            )
        s = self.settings
        cov = odometry_covariance(
            delta, s.odometry_sigma_m, s.odometry_sigma_per_m, s.odometry_sigma_rad,
            s.odometry_sigma_rad_per_rad, event.motion,
        )  # fmt: skip
        prev_key, key = pose_key(robot, previous), pose_key(robot, event.index)
        self._steps.setdefault(robot, {})[event.index] = _Step(previous, delta, cov)
        values = {}
        if key not in self.guesses:
            values = self._new_pose(key, se2.compose(self.guesses[prev_key], delta), "move")
        else:
            self._latest[robot] = event.index
        spec = FactorSpec("odometry", (prev_key, key), delta, cov, number)
        return Increment(number, (spec,), values)

    def _observe(self, event: Observe, number: int) -> Increment:
        s = self.settings
        (ra, ia), (rc, ic) = event.observer, event.observed
        ka, kc = pose_key(ra, ia), pose_key(rc, ic)
        if ra == rc:
            raise EstimationError(f"event {number}: robot {ra!r} cannot observe itself")
        z = (event.a_m, event.alpha_rad, event.b_m, event.beta_rad)
        _finite(number, "Observe measurement", np.asarray(z, dtype=float))
        if ka not in self.guesses and kc not in self.guesses:
            raise EstimationError(
                f"event {number}: neither {key_label(ka)} nor {key_label(kc)} is known; a mutual "
                "observation must involve a pose already in the graph"
            )
        try:
            check_observation(*z, s.beacon_offset_m)
        except EstimationError as exc:
            return self._reject(number, str(exc), (ka, kc))
        fix = localize_mutual(
            *z, s.beacon_offset_m, s.range_sigma_m, s.bearing_sigma_rad, s.gate_sigmas, "ml"
        )
        T, cov = mutual_between(fix.pose, fix.covariance, s.scanner_x_m)
        if not fix.accepted:
            return self._reject(
                number,
                f"s1/s2 gate: |s1 - s2| = {abs(fix.gap_m):.3f} m is {fix.gap_sigmas:.1f} sigma "
                f"(limit {s.gate_sigmas:g})",
                (ka, kc),
                T,
            )
        scale = self.mutual_scale()
        if fix.gap_sigmas > GAP_OUTLIER * scale:
            why = (f"s1/s2 gate: |s1 - s2| = {abs(fix.gap_m):.3f} m is {fix.gap_sigmas / scale:.1f}"
                   f" times the gaps' spread (limit {GAP_OUTLIER:g})")  # fmt: skip
            return self._reject(number, why, (ka, kc), T)
        predicted = self._predict(ra, ia, rc, ic)
        if predicted is not None:
            T_pred, cov_pred = predicted
            xi = se2.log(se2.between(T_pred, T))
            d2 = float(xi @ np.linalg.solve(cov_pred + cov, xi))
            if d2 > self._gate_chi2:
                return self._reject(
                    number,
                    f"prediction gate: Mahalanobis² {d2:.1f} against the pose predicted from "
                    f"the last fix and odometry (limit {self._gate_chi2:.1f})",
                    (ka, kc),
                    T,
                )
        values: dict[int, np.ndarray] = {}
        if kc not in self.guesses:
            values = self._new_pose(kc, se2.compose(self.guesses[ka], T), "observe")
        elif ka not in self.guesses:
            values = self._new_pose(ka, se2.compose(self.guesses[kc], se2.inverse(T)), "observe")
        elif self._sources[kc] == "move" and self._sources[ka] != "move":
            self._refine_guess(kc, se2.compose(self.guesses[ka], T), cov, "observe")
        elif self._sources[ka] == "move" and self._sources[kc] != "move":
            T_inv, cov_inv = _inverse_with_covariance(T, cov)
            self._refine_guess(ka, se2.compose(self.guesses[kc], T_inv), cov_inv, "observe")
        self._remember_fix(ra, ia, rc, ic, T, cov)
        self._gaps.append(fix.gap_sigmas)
        factor = FactorSpec("mutual", (ka, kc), T, cov * scale**2, number)
        return Increment(number, (factor,), values)

    def _localize(self, event: Localize, number: int) -> Increment:
        s = self.settings
        key = pose_key(event.robot, event.index)
        pdf = event.pdf
        if not isinstance(pdf, PosePdf):
            raise EstimationError(f"event {number}: Localize.pdf must be a PosePdf")
        reference = None if event.reference is None else pose_key(*event.reference)
        if reference is not None and reference not in self.guesses:
            raise EstimationError(
                f"event {number}: reference station {key_label(reference)} is not in the graph"
            )
        if reference == key:
            raise EstimationError(f"event {number}: a station cannot be localized against itself")
        mean = pdf.best_pose() if event.pose is None else np.asarray(event.pose, dtype=float)
        if mean.shape != (3,) or not np.isfinite(mean).all():
            raise EstimationError(f"event {number}: Localize.pose must be 3 finite numbers")
        radius_m, radius_rad = event.peak_radius or (s.peak_radius_m, s.peak_radius_rad)
        fitted = pdf.covariance(radius_m, radius_rad) if event.covariance is None else None
        cov_frame = (
            floor_covariance(fitted, s.global_min_sigma_m, s.global_min_sigma_rad)
            if fitted is not None
            else checked_covariance(event.covariance, f"event {number}: Localize.covariance")
        )
        cov = frame_to_body_covariance(float(mean[2]), cov_frame)
        base = np.zeros(3) if reference is None else self.guesses[reference]
        values: dict[int, np.ndarray] = {}
        fallback = self.guesses.get(key)
        fallback_in_ref = None if fallback is None else se2.between(base, fallback)
        seeded, from_search = seed_pose(
            pdf, fallback_in_ref, s.dominance_ratio, s.peak_radius_m, s.peak_radius_rad
        )
        if from_search and event.pose is not None:
            seeded = mean.copy()
        if key not in self.guesses:
            if seeded is None:
                return self._reject(
                    number,
                    f"{key_label(key)} is new and its search peak is not dominant (ratio "
                    f"{pdf.peak_ratio(s.peak_radius_m, s.peak_radius_rad):.2f} < "
                    f"{s.dominance_ratio:g}): nothing to seed it with",
                )
            values = self._new_pose(key, se2.compose(base, seeded), "localize")
        elif seeded is not None and from_search:
            self._refine_guess(key, se2.compose(base, seeded), cov, "localize")
        self.pdfs.setdefault(key, []).append((pdf, reference))
        keys = (key,) if reference is None else (reference, key)
        return Increment(number, (FactorSpec("global", keys, mean, cov, number),), values)

    # -- gate helpers ----------------------------------------------------------------------

    def _reject(
        self,
        number: int,
        reason: str,
        keys: tuple[int, ...] = (),
        measurement: np.ndarray | None = None,
    ) -> Increment:
        return Increment(number, rejection=Rejection(number, reason, keys, measurement))

    def _motion(self, robot: str, start: int, end: int) -> tuple[np.ndarray, np.ndarray] | None:
        """T_start_end of one robot by its odometry, with covariance; None if not chained."""
        if start == end:
            return np.zeros(3), np.zeros((3, 3))
        lo, hi = min(start, end), max(start, end)
        steps = self._steps.get(robot, {})
        chain: list[_Step] = []
        index = hi
        while index != lo:
            step = steps.get(index)
            if step is None or step.previous < lo:
                return None
            chain.append(step)
            index = step.previous
        T, cov = np.zeros(3), np.zeros((3, 3))
        for step in reversed(chain):
            T, cov = se2.propagate_compose(T, cov, step.delta, step.covariance)
        return (T, cov) if start < end else _inverse_with_covariance(T, cov)

    def _remember_fix(
        self, ra: str, ia: int, rc: str, ic: int, T: np.ndarray, cov: np.ndarray
    ) -> None:
        if ra < rc:
            self._fixes[(ra, rc)] = (ia, ic, T, cov)
        else:
            T_inv, cov_inv = _inverse_with_covariance(T, cov)
            self._fixes[(rc, ra)] = (ic, ia, T_inv, cov_inv)

    def _fix(self, ra: str, rc: str) -> tuple[int, int, np.ndarray, np.ndarray] | None:
        """The last accepted fix between two robots as (A's index, C's index, T_A_C, its
        covariance); None if they have none."""
        if ra < rc:
            return self._fixes.get((ra, rc))
        last = self._fixes.get((rc, ra))
        if last is None:
            return None
        jc, ja, T_ca, cov_ca = last
        return (ja, jc, *_inverse_with_covariance(T_ca, cov_ca))

    def _predict(self, ra: str, ia: int, rc: str, ic: int) -> tuple[np.ndarray, np.ndarray] | None:
        """T_A_C predicted from the last accepted fixes and odometry: through the two robots'
        own last fix, or through a third robot B's last fixes with each (A–B, B's odometry,
        B–C), whichever is the tightest (least determinant). The pair's own fix may be many
        metres of driving old while both saw B since (generated building 402, three robots:
        a and c had last seen each other before 6 and 8.5 m of driving, 16° of heading apart
        that way, and a false observation 52° off passed; through b, which had just seen
        both, it was 10°)."""
        best, least = None, math.inf
        for path in [(ra, rc), *((ra, rb, rc) for rb in self._latest if rb not in (ra, rc))]:
            predicted = self._through(path, ia, ic)
            if predicted is not None and (det := float(np.linalg.det(predicted[1]))) < least:
                best, least = predicted, det
        return best

    def _through(
        self, robots: tuple[str, ...], ia: int, ic: int
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """T_A_C (A = ``robots[0]`` at pose ``ia``, C = ``robots[-1]`` at ``ic``) chained
        through each consecutive pair's last fix and each robot's odometry between its fixes,
        with covariance (the links taken as independent); None where a link is missing."""
        T, cov = np.zeros(3), np.zeros((3, 3))
        robot, index = robots[0], ia
        for other in robots[1:]:
            fix = self._fix(robot, other)
            motion = None if fix is None else self._motion(robot, index, fix[0])
            if fix is None or motion is None:
                return None
            T, cov = se2.propagate_compose(T, cov, *motion)
            T, cov = se2.propagate_compose(T, cov, fix[2], fix[3])
            robot, index = other, fix[1]
        motion = self._motion(robot, index, ic)
        return None if motion is None else se2.propagate_compose(T, cov, *motion)


def _finite(number: int, what: str, values: np.ndarray) -> None:
    if values.shape != (3,) and values.shape != (4,):
        raise EstimationError(f"event {number}: {what} has shape {values.shape}")
    if not np.isfinite(values).all():
        raise EstimationError(f"event {number}: {what} holds NaN or inf: {values.tolist()}")
