"""The rotating-mirror 3D scanner (docs/design.md §3, the paper's eq. 4 with its typo corrected).

A planar two-sided mirror turns about an axis parallel to the scanner's y axis, ``d`` in front
of the scanner origin. A beam of range r and bearing θ meets the mirror at x = d and continues
r − d/cos θ along the reflected direction, so it ends at (paper eq. 4, corrected)::

    x = d + (r cos θ − d) cos φ,   y = r sin θ,   z = (r cos θ − d) sin φ

(the paper prints ``sin θ`` in z: a typo). Reflection doubles angles: with the mirror at angle
ψ from edge-on, the folded scan plane rises to φ = 2ψ + φ0. Edge-on (ψ ≡ 0 mod π) the mirror's
edge blocks the central beams — the signature of the absolute phase — and φ = φ0.

Kinematics: a motor turns the mirror through a gearbox (``gear_ratio`` motor turns per mirror
turn); a blocking arm on the motor shaft covers the right-most beams once per motor turn. The
falling edges of the arm (long range → very short range) give the motor period and phase; the
edge-on signature picks the motor turn at which the mirror is edge-on, whose exact motor phase
is a calibration constant (``edge_on_motor_phase``), so the mirror angle at any time follows
from the arm's precise timing rather than the coarse edge-on one. Since the mirror has two
faces, one sweep of the valid elevations recurs every half mirror turn; the sweep is centred on
the edge-on moment.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from sensors.errors import SensorError
from sensors.lms200.protocol.scan import REFLECTOR_MODES, Scan, SpecialCode
from sensors.lms200.protocol.telegram import TURN_S

__all__ = [
    "MirrorEstimate",
    "MirrorGeometry",
    "Scan3D",
    "ScanClock",
    "arm_blocked",
    "assemble_sweeps",
    "edge_on_times",
    "elevation_at",
    "estimate_mirror",
    "fit_motor",
    "mirror_points",
    "scan_times",
]


@dataclass(frozen=True)
class MirrorGeometry:
    """The mechanics and calibration of one rotating-mirror scanner (SI units, radians)."""

    axis_offset_m: float  # d
    gear_ratio: float  # motor turns per mirror turn
    nominal_motor_period_s: float
    elevation_offset_rad: float = 0.0  # φ0
    elevation_min_rad: float = -math.pi / 2
    elevation_max_rad: float = math.pi / 2
    arm_samples: int = 3
    arm_max_range_m: float = 0.25
    edge_on_half_width_rad: float = math.radians(3.0)
    edge_on_beams_rad: float = math.radians(30.0)
    edge_on_motor_phase_rad: float | None = 0.0  # None: not calibrated, use the coarse phase

    @property
    def half_turn_motor_turns(self) -> float:
        """Motor turns per half mirror turn: one sweep of the elevations."""
        return self.gear_ratio / 2.0


def mirror_points(
    range_m: np.ndarray, bearing_rad: np.ndarray, elevation_rad: np.ndarray, axis_offset_m: float
) -> np.ndarray:
    """Paper eq. 4 (corrected): (N, 3) points in the scanner frame from r, θ and φ."""
    d = axis_offset_m
    folded = range_m * np.cos(bearing_rad) - d
    return np.column_stack(
        [
            d + folded * np.cos(elevation_rad),
            range_m * np.sin(bearing_rad),
            folded * np.sin(elevation_rad),
        ]
    )


def scan_times(scans: list[Scan]) -> np.ndarray:
    """Measurement times of consecutive scans (s, in the host clock).

    With real-time indices (the scanner's mirror-turn counter mod 256) the spacing is exact:
    the counter is unwrapped using the host stamps to resolve gaps of 256 turns and more, and
    the times are anchored so that they lie at or before the host stamps. Without them, the
    host receive stamps are used as they are.
    """
    clock = ScanClock()
    clock.extend(scans)  # SensorError on a scan without a (finite) host stamp
    return clock.times()


class ScanClock:
    """:func:`scan_times` of a stream that grows scan by scan: the times of all scans so far,
    equal to ``scan_times`` of the same scans (the anchor is the running minimum)."""

    def __init__(self) -> None:
        self.stamps: list[float] = []
        self.turns: list[int] = []
        self.indexed = True
        self._index = 0
        self._anchor = math.inf

    def add(self, scan: Scan) -> None:
        self.extend((scan,))

    def extend(self, scans: Sequence[Scan]) -> None:
        """Add ``scans`` in order, over arrays (a capture has tens of thousands). Each scan's
        turn counts on from the one before: the step of the counter mod 256, plus the whole
        wraps of 256 turns that the stamps' gap holds. SensorError at the first scan without a
        host stamp, the scans before it added."""
        stamps = [scan.stamp_s for scan in scans]
        if None in stamps:
            self.extend(scans[: stamps.index(None)])
            raise SensorError("every scan needs a host stamp to be placed in time")
        stamped = [float(stamp) for stamp in stamps]  # type: ignore[arg-type]
        if not all(math.isfinite(stamp) for stamp in stamped):
            raise SensorError("a scan's host stamp is not a finite time")
        if self.indexed:
            indices = [scan.scan_index for scan in scans]
            counted = indices.index(None) if None in indices else len(indices)
            if counted:
                self._count(np.array(indices[:counted], np.int64), np.array(stamped[:counted]))
            self.indexed = counted == len(indices)
        self.stamps += stamped

    def _count(self, index: np.ndarray, stamp: np.ndarray) -> None:
        """Turns of scans with these counter values and stamps, after those so far."""
        before = 1 if self.turns else 0
        if before:
            index = np.concatenate([[self._index], index])
            stamp = np.concatenate([[self.stamps[-1]], stamp])
        step = np.diff(index) % 256
        expected = np.diff(stamp) / TURN_S
        wraps = np.maximum(0.0, np.round((expected - step) / 256)).astype(np.int64)
        first = self.turns[-1] if before else 0
        turns = first + np.concatenate([[0], np.cumsum(step + 256 * wraps)])
        self.turns += turns[before:].tolist()
        self._index = int(index[-1])
        self._anchor = min(self._anchor, float(np.min(stamp - turns * TURN_S)))

    def times(self) -> np.ndarray:
        if not self.indexed or not self.stamps:
            return np.array(self.stamps, dtype=float)
        return np.asarray(np.array(self.turns, dtype=np.int64) * TURN_S + self._anchor)


def _variants(scans: list[Scan]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The scans grouped by their (shared, read-only) bearing array: per group the scans'
    indices, the bearings and the ranges stacked (scans × samples), so that a test over each
    scan's samples is one array operation (a sweep has hundreds of scans)."""
    groups: dict[int, list[int]] = {}
    for k, scan in enumerate(scans):
        groups.setdefault(id(scan.bearing_rad), []).append(k)
    return [
        (np.array(rows), scans[rows[0]].bearing_rad, np.stack([scans[k].ranges_m for k in rows]))
        for rows in groups.values()
    ]


def arm_blocked(scans: list[Scan], arm_samples: int, arm_max_range_m: float) -> np.ndarray:
    """Whether the blocking arm covers each scan's right-most samples."""
    blocked = np.zeros(len(scans), dtype=bool)
    for rows, _, ranges in _variants(scans):
        right = ranges[:, :arm_samples]
        blocked[rows] = np.count_nonzero(right < arm_max_range_m, axis=1) * 2 > arm_samples
    return blocked


@dataclass(frozen=True)
class MotorFit:
    period_s: float
    phase_time_s: float  # a time at which the arm starts to block (motor angle 0)
    edges_used: int
    edges_rejected: int
    residual_rms_s: float


def fit_motor(edge_times_s: np.ndarray, nominal_period_s: float) -> MotorFit:
    """Motor period and phase from arm-edge times, robust to missed and spurious edges.

    Each edge is numbered by its motor turn, counting on from the previous accepted edge with the
    current period estimate (so a missed edge skips a number); edges that fall far from a whole
    turn are spurious and rejected. A least-squares line through (turn, time) gives the period.
    """
    times = np.sort(np.asarray(edge_times_s, dtype=float))
    if len(times) < 3:
        raise SensorError(f"need at least 3 arm edges to estimate the motor rate, got {len(times)}")
    period = nominal_period_s
    turns = [0]
    kept = [times[0]]
    rejected = 0
    # The least-squares slope of (turn, time) so far, updated edge by edge (Welford's running
    # means and co-moments: a polyfit per edge cost 0.4 s of a 150-sweep mission).
    mean_n, mean_t, c_nn, c_nt = 0.0, float(times[0]), 0.0, 0.0
    for t in times[1:]:
        steps = (t - kept[-1]) / period
        n = round(steps)
        if n < 1 or abs(steps - n) > 0.3:
            rejected += 1
            continue
        turns.append(turns[-1] + n)
        kept.append(t)
        count = len(kept)
        dn, dt = turns[-1] - mean_n, float(t) - mean_t
        mean_n += dn / count
        mean_t += dt / count
        c_nn += dn * (turns[-1] - mean_n)
        c_nt += dn * (float(t) - mean_t)
        if count >= 3:
            period = c_nt / c_nn
    # A spurious first edge shifts every number: refit from the consensus and recount.
    slope, intercept = np.polyfit(turns, kept, 1)
    residual = np.asarray(kept) - (slope * np.asarray(turns) + intercept)
    good = np.abs(residual) < 0.25 * slope
    if good.sum() < 3:
        raise SensorError("arm edges are too irregular to estimate the motor rate")
    slope, intercept = np.polyfit(np.asarray(turns)[good], np.asarray(kept)[good], 1)
    residual = np.asarray(kept)[good] - (slope * np.asarray(turns)[good] + intercept)
    return MotorFit(
        period_s=float(slope),
        phase_time_s=float(intercept),
        edges_used=int(good.sum()),
        edges_rejected=rejected + int((~good).sum()),
        residual_rms_s=float(np.sqrt(np.mean(residual**2))),
    )


def edge_on_times(scans: list[Scan], times_s: np.ndarray, geometry: MirrorGeometry) -> np.ndarray:
    """Centres of the runs of scans whose central beams are blocked by the mirror's edge."""
    blocked = np.zeros(len(scans), dtype=bool)
    limit = geometry.axis_offset_m * 1.5 + 0.05
    for rows, bearings, ranges in _variants(scans):
        central = np.abs(bearings) < geometry.edge_on_beams_rad * 0.8
        if central.any():
            short = np.count_nonzero(ranges[:, central] < limit, axis=1)
            blocked[rows] = short > 0.8 * np.count_nonzero(central)
    centres = []
    k = 0
    while k < len(blocked):
        if blocked[k]:
            j = k
            while j + 1 < len(blocked) and blocked[j + 1]:
                j += 1
            # Half a scan interval beyond each end of the run, where the signature began/ended.
            before = times_s[k - 1] if k > 0 else times_s[k]
            after = times_s[j + 1] if j + 1 < len(blocked) else times_s[j]
            centres.append(0.25 * (before + times_s[k] + times_s[j] + after))
            k = j + 1
        else:
            k += 1
    return np.asarray(centres)


@dataclass(frozen=True)
class MirrorEstimate:
    """The mirror's state over a stretch of scans: φ(t) follows from it."""

    motor_period_s: float
    motor_phase_time_s: float
    edge_on_time_s: float  # a moment at which the mirror is edge-on
    fine_phase: bool  # edge-on time taken from the arm's phase (calibrated), not coarse
    edges_used: int
    edges_rejected: int
    geometry: MirrorGeometry

    @property
    def motor_rate_hz(self) -> float:
        return 1.0 / self.motor_period_s

    @property
    def sweep_period_s(self) -> float:
        """Half a mirror turn: the time between two sweeps."""
        return self.motor_period_s * self.geometry.half_turn_motor_turns


def estimate_mirror(
    scans: list[Scan], times_s: np.ndarray, geometry: MirrorGeometry
) -> MirrorEstimate:
    """Motor rate and phase from the arm, absolute mirror phase from the edge-on signature."""
    blocked = arm_blocked(scans, geometry.arm_samples, geometry.arm_max_range_m)
    falling = np.flatnonzero(blocked[1:] & ~blocked[:-1]) + 1
    edges = 0.5 * (times_s[falling - 1] + times_s[falling])
    motor = fit_motor(edges, geometry.nominal_motor_period_s)
    coarse = edge_on_times(scans, times_s, geometry)
    if len(coarse) == 0:
        raise SensorError(
            "no edge-on signature (central beams blocked by the mirror's edge) in these scans: "
            "the absolute mirror phase is unknown"
        )
    # Combine every edge-on event: they recur each half mirror turn.
    half = motor.period_s * geometry.half_turn_motor_turns
    reference = coarse[0] + half * np.round((coarse - coarse[0]) / half)
    edge_on = float(coarse[0] + np.mean(coarse - reference))
    fine = (
        geometry.edge_on_motor_phase_rad is not None
        and float(geometry.half_turn_motor_turns).is_integer()
    )
    if fine:
        phase = geometry.edge_on_motor_phase_rad / (2 * math.pi)  # type: ignore[operator]
        turn = round((edge_on - motor.phase_time_s) / motor.period_s - phase)
        edge_on = motor.phase_time_s + motor.period_s * (turn + phase)
    return MirrorEstimate(
        motor_period_s=motor.period_s,
        motor_phase_time_s=motor.phase_time_s,
        edge_on_time_s=edge_on,
        fine_phase=fine,
        edges_used=motor.edges_used,
        edges_rejected=motor.edges_rejected,
        geometry=geometry,
    )


def elevation_at(times_s: np.ndarray, estimate: MirrorEstimate) -> np.ndarray:
    """φ(t) = 2ψ(t) + φ0, wrapped to (−π, π]; ψ = 0 at the edge-on moment."""
    psi = math.pi * (np.asarray(times_s) - estimate.edge_on_time_s) / estimate.sweep_period_s
    phi = 2.0 * psi + estimate.geometry.elevation_offset_rad
    return np.asarray(np.angle(np.exp(1j * phi)))


@dataclass(frozen=True)
class Scan3D:
    """One sweep of the folded scan plane: 3D points in the scanner frame, with provenance."""

    points_scanner: np.ndarray  # (N, 3)
    range_m: np.ndarray  # (N,)
    bearing_rad: np.ndarray  # (N,)
    elevation_rad: np.ndarray  # (N,)
    reflector: np.ndarray  # (N,) bool
    flags: np.ndarray  # (N,) uint8
    stamp_s: np.ndarray  # (N,) time of the scan each point came from
    start_s: float
    end_s: float
    scans: int

    def __len__(self) -> int:
        return len(self.points_scanner)

    def trimmed(self) -> Scan3D:
        """The sweep with its points (in float32: rounded by at most 4 µm at the LMS's 80 m,
        0.5 µm within 8 m; its ranges come in millimetres) and reflector marks only, the other
        per-point fields empty: what the estimator keeps of a dwell's sweep, a quarter of its
        memory (the sweeps' points were 250 MB of a 16-room mission's batch in float64)."""
        empty = np.zeros(0)
        return replace(self, points_scanner=self.points_scanner.astype(np.float32),
                       range_m=empty, bearing_rad=empty, elevation_rad=empty,
                       flags=np.zeros(0, np.uint8), stamp_s=empty)  # fmt: skip


def assemble_sweeps(
    scans: list[Scan], times_s: np.ndarray, estimate: MirrorEstimate, *, min_scans: int = 10
) -> list[Scan3D]:
    """Cut the scans into sweeps (one per half mirror turn) and convert them to 3D points.

    Left out: elevations outside the valid sweep, the edge-on blind spot, the samples the arm
    covers, invalid ranges, and returns nearer than the mirror.
    """
    geometry = estimate.geometry
    phi = elevation_at(times_s, estimate)
    valid_phase = (phi >= geometry.elevation_min_rad) & (phi <= geometry.elevation_max_rad)
    blind = np.abs(phi - geometry.elevation_offset_rad) < 2.0 * geometry.edge_on_half_width_rad
    sweep_index = np.floor(
        (np.asarray(times_s) - estimate.edge_on_time_s) / estimate.sweep_period_s + 0.5
    ).astype(np.int64)
    sweeps: list[Scan3D] = []
    for index in np.unique(sweep_index[valid_phase]):
        rows = np.flatnonzero(valid_phase & ~blind & (sweep_index == index))
        if len(rows) < min_scans:
            continue
        r, b, e, f, m, t = _samples([scans[k] for k in rows], phi[rows], times_s[rows], geometry)
        sweeps.append(
            Scan3D(
                points_scanner=mirror_points(r, b, e, geometry.axis_offset_m),
                range_m=r,
                bearing_rad=b,
                elevation_rad=e,
                reflector=m,
                flags=f,
                stamp_s=t,
                start_s=float(times_s[rows[0]]),
                end_s=float(times_s[rows[-1]]),
                scans=len(rows),
            )
        )
    return sweeps


def _samples(
    scans: list[Scan], phi: np.ndarray, times_s: np.ndarray, geometry: MirrorGeometry
) -> tuple[np.ndarray, ...]:
    """(range, bearing, elevation, flags, reflector, stamp) of the samples a sweep keeps from
    its ``scans`` (taken at elevations ``phi`` and times ``times_s``), in scan order: valid,
    not under the arm, farther than the mirror. One array operation when the scans share their
    variant and measuring mode (a sweep's hundreds of scans do), else scan by scan."""
    first = scans[0]
    if all(s.bearing_rad is first.bearing_rad and s.measuring_mode == first.measuring_mode
           for s in scans):  # fmt: skip
        ranges = np.stack([s.ranges_m for s in scans])
        flags = np.stack([s.flags for s in scans])
        keep = np.stack([s.code for s in scans]) == SpecialCode.VALID
        keep[:, : geometry.arm_samples] = False
        keep &= ranges * np.cos(first.bearing_rad) > geometry.axis_offset_m + 0.02
        counts = np.count_nonzero(keep, axis=1)
        kept_flags = flags[keep]
        reflector = (
            kept_flags > 0
            if first.measuring_mode in REFLECTOR_MODES
            else np.zeros(len(kept_flags), dtype=bool)
        )
        bearings = np.broadcast_to(first.bearing_rad, ranges.shape)[keep]
        return (ranges[keep], bearings, np.repeat(phi, counts), kept_flags, reflector,
                np.repeat(times_s, counts))  # fmt: skip
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("r", "b", "e", "f", "m", "t")}
    for scan, elevation, time_s in zip(scans, phi, times_s, strict=True):
        keep = scan.valid.copy()
        keep[: geometry.arm_samples] = False
        keep &= scan.ranges_m * np.cos(scan.bearing_rad) > geometry.axis_offset_m + 0.02
        parts["r"].append(scan.ranges_m[keep])
        parts["b"].append(scan.bearing_rad[keep])
        parts["e"].append(np.full(np.count_nonzero(keep), elevation))
        parts["f"].append(scan.flags[keep])
        parts["m"].append(scan.reflector[keep])
        parts["t"].append(np.full(np.count_nonzero(keep), time_s))
    return tuple(np.concatenate(parts[key]) for key in ("r", "b", "e", "f", "m", "t"))
