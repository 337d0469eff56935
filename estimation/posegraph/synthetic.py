"""Synthetic two-robot leapfrog missions: event streams with ground truth, for tests and benches.

Robot ``a`` is the reference: it stands at a station while robot ``b`` takes scans around it
(walking round it, 1-3 m between scans), each with a mutual observation; then ``a`` moves on to
the next station, watched by ``b`` (paper Fig. 2). Stations follow a 30 m × 20 m rectangular
loop, lap after lap, so later laps revisit earlier stations. Stations are globally localized:
against a fixed prior map every ``map_prior_every`` stations, and against the nearest station of
an earlier lap (a loop closure).

Measurements are drawn from exactly the noise models the graph assumes (calibrated sigmas):
odometry per :func:`~estimation.posegraph.graph.odometry_covariance`, range/bearing of each beacon,
and search PDFs (a Gaussian on a 0.5σ lattice aligned to the map grid, like a real search's). Gross
outliers are added so that ``outlier_fraction`` of the mutual and global events are wrong: a second
mutual observation of a wrong but self-consistent geometry (it passes the s1/s2 check), or a second
search result that matched the wrong place. They are drawn from their own random generator: with or
without them, the correct events are the same.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimation.posegraph.events import Event, Localize, Move, Observe, Start
from estimation.posegraph.graph import GraphSettings, odometry_covariance
from estimation.posegraph.keys import pose_key
from estimation.posegraph.mutual import measurements
from estimation.posepdf import PosePdf
from sensors.geometry import se2

__all__ = [
    "Scenario",
    "leapfrog",
    "mutual_measurements",
    "search_pdf",
    "visible",
]

_LOOP_W_M, _LOOP_H_M = 30.0, 20.0


@dataclass(frozen=True)
class Scenario:
    """An event stream, the true pose of every key, and which events are gross outliers."""

    events: tuple[Event, ...]
    truth: dict[int, np.ndarray]
    outliers: frozenset[int]
    mutual_events: int
    global_events: int

    def truth_array(self, keys: list[int]) -> np.ndarray:
        return np.array([self.truth[k] for k in keys])


def _loop_point(arc_m: float) -> tuple[float, float, float]:
    """Position and heading at arc length ``arc_m`` along the loop's rectangle."""
    perimeter = 2 * (_LOOP_W_M + _LOOP_H_M)
    s = arc_m % perimeter
    for length, (x0, y0), heading in (
        (_LOOP_W_M, (0.0, 0.0), 0.0),
        (_LOOP_H_M, (_LOOP_W_M, 0.0), math.pi / 2),
        (_LOOP_W_M, (_LOOP_W_M, _LOOP_H_M), math.pi),
        (_LOOP_H_M, (0.0, _LOOP_H_M), -math.pi / 2),
    ):
        if s <= length:
            return x0 + s * math.cos(heading), y0 + s * math.sin(heading), heading
        s -= length
    return 0.0, 0.0, 0.0


def visible(T_map_a: np.ndarray, T_map_c: np.ndarray, settings: GraphSettings) -> bool:
    """Whether each robot's scanner sees the other's beacon: in range, outside the ±10° blind
    wedge straight ahead, and the beacons well apart."""
    z = mutual_measurements(T_map_a, T_map_c, settings)
    a, alpha, b, beta = z
    wedge = math.radians(10.0)
    return bool(0.5 < a < 7.5 and 0.5 < b < 7.5 and abs(alpha) > wedge and abs(beta) > wedge)


def mutual_measurements(
    T_map_a: np.ndarray, T_map_c: np.ndarray, settings: GraphSettings
) -> np.ndarray:
    """Noise-free (a, α, b, β) between two robot poses (scanner ``scanner_x_m`` ahead)."""
    T_r_s = np.array([settings.scanner_x_m, 0.0, 0.0])
    T_sa_sc = se2.between(se2.compose(T_map_a, T_r_s), se2.compose(T_map_c, T_r_s))
    return np.asarray(measurements(T_sa_sc, settings.beacon_offset_m))


def search_pdf(pose: np.ndarray, sigma_m: float, sigma_rad: float, half_width: int = 6) -> PosePdf:
    """A search-like PDF: a Gaussian at ``pose`` on a σ/2 lattice aligned to multiples of the
    step, ``half_width`` steps either side of the nearest lattice point."""
    step_m, step_rad = sigma_m / 2, sigma_rad / 2
    offsets = np.arange(-half_width, half_width + 1)
    x_m = step_m * (round(pose[0] / step_m) + offsets)
    y_m = step_m * (round(pose[1] / step_m) + offsets)
    yaw_rad = step_rad * (round(pose[2] / step_rad) + offsets)
    cov = np.diag([sigma_m**2, sigma_m**2, sigma_rad**2])
    return PosePdf.from_gaussian(pose, cov, x_m, y_m, yaw_rad)


def _triple(values: np.ndarray) -> tuple[float, float, float]:
    x, y, yaw = (float(v) for v in values)
    return x, y, yaw


def _odometry(rng: np.random.Generator, delta: np.ndarray, s: GraphSettings) -> np.ndarray:
    cov = odometry_covariance(
        delta, s.odometry_sigma_m, s.odometry_sigma_per_m, s.odometry_sigma_rad,
        s.odometry_sigma_rad_per_rad,
    )  # fmt: skip
    return se2.compose(delta, rng.multivariate_normal(np.zeros(3), cov))


def leapfrog(
    stations: int,
    scans_per_station: int,
    seed: int = 0,
    settings: GraphSettings | None = None,
    global_sigma_m: float = 0.05,
    global_sigma_rad: float = math.radians(1.0),
    map_prior_every: int = 1,
    loop_closures: bool = True,
    outlier_fraction: float = 0.0,
    station_spacing_m: float = 3.0,
) -> Scenario:
    """A two-robot leapfrog mission of ``stations × (1 + scans_per_station)`` poses."""
    s = settings or GraphSettings()
    rng = np.random.default_rng(seed)
    events: list[Event] = []
    truth: dict[int, np.ndarray] = {}
    outliers: set[int] = set()
    counts = {"mutual": 0, "global": 0}

    # Outliers come from their own generator, so that a mission with outliers holds exactly the
    # events of the same mission without them, plus the wrong ones.
    wrong_rng = np.random.default_rng([seed, 1])
    extra = outlier_fraction / (1.0 - outlier_fraction)

    def gross_offset() -> np.ndarray:
        shift = wrong_rng.uniform(1.0, 5.0) * np.exp(1j * wrong_rng.uniform(-math.pi, math.pi))
        return np.array([shift.real, shift.imag, wrong_rng.uniform(-math.pi, math.pi)])

    def observe(ia: int, ib: int, first: bool = False) -> None:
        ka, kb = pose_key("a", ia), pose_key("b", ib)
        T_a, T_b = truth[ka], truth[kb]
        if not visible(T_a, T_b, s):
            return
        noise = np.array([s.range_sigma_m, s.bearing_sigma_rad] * 2)
        z = mutual_measurements(T_a, T_b, s) + rng.normal(0.0, 1.0, 4) * noise
        events.append(Observe(("a", ia), ("b", ib), *(float(v) for v in z)))
        counts["mutual"] += 1
        if first or wrong_rng.random() >= extra:
            return
        while True:  # a wrong, self-consistent geometry: C displaced 1-5 m and turned
            T_wrong = se2.compose(gross_offset(), T_b)
            if visible(T_a, T_wrong, s):
                break
        z = mutual_measurements(T_a, T_wrong, s) + wrong_rng.normal(0.0, 1.0, 4) * noise
        outliers.add(len(events))
        events.append(Observe(("a", ia), ("b", ib), *(float(v) for v in z)))
        counts["mutual"] += 1

    def localize(ia: int, reference: int | None) -> None:
        key = pose_key("a", ia)
        base = np.zeros(3) if reference is None else truth[pose_key("a", reference)]
        true_rel = se2.between(base, truth[key])
        cov = np.diag([global_sigma_m**2, global_sigma_m**2, global_sigma_rad**2])
        ref = None if reference is None else ("a", reference)
        noisy = true_rel + rng.multivariate_normal(np.zeros(3), cov)
        events.append(Localize("a", ia, search_pdf(noisy, global_sigma_m, global_sigma_rad), ref))
        counts["global"] += 1
        if wrong_rng.random() >= extra:
            return
        wrong = true_rel + gross_offset()  # the search matched the wrong place
        wrong[2] = float(se2.wrap_angle(wrong[2]))
        outliers.add(len(events))
        events.append(Localize("a", ia, search_pdf(wrong, global_sigma_m, global_sigma_rad), ref))
        counts["global"] += 1

    def station_pose(i: int) -> np.ndarray:
        x, y, heading = _loop_point(i * station_spacing_m)
        return np.array(
            [
                x + rng.normal(0.0, 0.3),
                y + rng.normal(0.0, 0.3),
                float(se2.wrap_angle(heading + rng.normal(0.0, math.radians(20.0)))),
            ]
        )

    def scan_pose(T_a: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
        """b walks around a: the next scan 25-60° further round a ring of 1.5-3.5 m, facing
        along the ring give or take 60° (both beacons visible)."""
        start = rng.uniform(-math.pi, math.pi)
        if previous is not None:
            start = math.atan2(previous[1] - T_a[1], previous[0] - T_a[0])
        while True:
            r = rng.uniform(1.5, 3.5)
            phi = start + rng.uniform(math.radians(25), math.radians(60))
            heading = phi + math.pi / 2 + rng.uniform(-math.radians(60), math.radians(60))
            T_b = np.array(
                [T_a[0] + r * math.cos(phi), T_a[1] + r * math.sin(phi), se2.wrap_angle(heading)]
            )
            if visible(T_a, T_b, s):
                return T_b

    ib = -1
    for ia in range(stations):
        T_a = station_pose(ia)
        truth[pose_key("a", ia)] = T_a
        if ia == 0:
            events.append(Start("a", 0, _triple(T_a)))
        else:
            true_delta = se2.between(truth[pose_key("a", ia - 1)], T_a)
            events.append(Move("a", ia, _triple(_odometry(rng, true_delta, s))))
            observe(ia, ib)  # b watches a arrive
        for _ in range(scans_per_station):
            T_b = scan_pose(T_a, truth[pose_key("b", ib)] if ib >= 0 else None)
            ib += 1
            truth[pose_key("b", ib)] = T_b
            if ib == 0:
                observe(ia, ib, first=True)
                continue
            true_delta = se2.between(truth[pose_key("b", ib - 1)], T_b)
            events.append(Move("b", ib, _triple(_odometry(rng, true_delta, s))))
            observe(ia, ib)
        if map_prior_every and ia % map_prior_every == 0 and ia > 0:
            localize(ia, None)
        if loop_closures and ia > 0:
            earlier = [
                j
                for j in range(ia - 1)
                if np.hypot(*(truth[pose_key("a", j)][:2] - T_a[:2])) < 2.0 and ia - j > 5
            ]
            if earlier:
                localize(ia, earlier[-1])
    return Scenario(
        events=tuple(events),
        truth=truth,
        outliers=frozenset(outliers),
        mutual_events=counts["mutual"],
        global_events=counts["global"],
    )
