"""The estimator's event stream of a mission (docs/design.md §8), made one dataset event at a
time.

A gauge prior on the first robot's start; odometry between each robot's stops, as uncertain as
the motion driven along the way; the mutual observations of every dwell between its reference and
mapper, each beacon chosen as the estimate so far predicts it (gated by s1/s2 in the graph
builder). ``batch`` makes the stream of a recorded dataset; the mission loop makes it as the
mission goes, from the same code.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from estimation.app.config import Config
from estimation.app.dataset import Dataset, Progress, RobotStream, Sweep
from estimation.app.rig import T_robot_scanner, beacon_parameters, graph_settings
from estimation.chi2 import chi2_quantile
from estimation.posegraph.events import Event, Move, Observe, Start
from estimation.posegraph.graph import GraphBuilder, GraphSettings
from estimation.posegraph.keys import pose_key
from estimation.posegraph.mutual import (
    closure_distance,
    gap_sigma,
    separations,
    sighting_distance,
)
from sensors.geometry import se2
from sensors.geometry.frames import pose2_matrix
from sensors.scan3d.beacon import BeaconDetection, detect_beacons
from sensors.trajio import pose_at

__all__ = ["Counts", "EventMaker", "EventStream", "build_events"]

#: χ² (3 degrees of freedom) within which three robots' mutual observations close.
_CLOSURE_CHI2 = chi2_quantile(0.999, 3)
#: χ² (2 degrees of freedom) within which a one-way sighting lies where two observations put it.
_SIGHTING_CHI2 = chi2_quantile(0.999, 2)
#: Assignments of a dwell's detections tried for closure at most (a bound on the work).
_CLOSURE_MAX = 100_000
#: A detection is a third robot's beacon when the estimate places that beacon this near it
#: (m, range and bearing times range) and the partner's at least ``_PARTNER_FAR_M`` away.
_THIRD_NEAR_M, _PARTNER_FAR_M = 0.15, 0.5
#: A partner's beacon has left the place where it stood when its odometry moved it this far
#: (m): four times the 5 cm of range within which two detections count as the same.
_MOVED_M = 0.2


@dataclass(frozen=True)
class Counts:
    """What the event stream made of the dataset's dwells."""

    dwells: int
    observations: int
    missing_sweeps: tuple[str, ...]  # "a3 (dwell 7): why"
    unseen: tuple[str, ...]  # "a3–b4": a pair whose beacons were not both found
    moves_before_first_fix: int  # odometry held back until its robot was anchored


@dataclass(frozen=True)
class EventStream:
    """The estimator's event stream of a dataset, the sweeps, the counts, and the graph builder
    that consumed the events (its guesses are the estimate so far)."""

    events: list[Event]
    sweeps: list[Sweep]
    counts: Counts
    builder: GraphBuilder


class EventMaker:
    """The estimator's event stream of a mission, made one dataset event (an ``events.jsonl``
    entry) at a time, as :func:`build_events` reads a recorded mission and the mission loop
    runs a live one. A builder consumes the events as they are made, so that each observation
    can be matched to the beacon predicted by the estimate so far.

    ``odometry`` maps each robot to its odometry so far (stamps, poses); a move is fed once the
    odometry covers its end. ``streams`` (each robot's decoded LMS stream so far) are passed to
    :meth:`feed`, since they grow."""

    def __init__(self, config: Config, robots: list[str], starts: dict[str, np.ndarray],
                 odometry: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:  # fmt: skip
        self.config, self.robots, self.odometry = config, robots, odometry
        self.builder = GraphBuilder(graph_settings(config))
        self.params = beacon_parameters(config)
        self.events: list[Event] = []
        self.sweeps: list[Sweep] = []
        self.dwells = self.observations = self.held_back = 0
        self.missing: list[str] = []
        self.unseen: list[str] = []
        # Odometry of a robot that moved before its first fix: (to_index, delta) per robot.
        self.pending: dict[str, list[Move]] = {}
        # (observer's key, observed's key) -> the observer's detection of the observed's beacon
        # (range, bearing) in an accepted mutual observation: two robots that have not moved
        # since see each other's beacons there again.
        self.held: dict[tuple[int, int], tuple[float, float]] = {}
        # Each robot's last sweep: (its pose index, its detections, every robot's pose index).
        self.last: dict[str, tuple[int, list[BeaconDetection], dict[str, int]]] = {}
        # (robot, pose index) -> the robot's odometry pose there: how far its beacon moved.
        self.odometry_at: dict[tuple[str, int], np.ndarray] = {}
        # robot -> (its odometry poses, their yaw unwrapped): made again when the poses change.
        self._yaw: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        gauge = robots[0]
        self._emit(Start(gauge, 0, tuple(float(v) for v in starts[gauge])))  # type: ignore[arg-type]

    def _emit(self, event: Event) -> bool:
        """Consume an event; True if it gave the graph a factor."""
        increment = self.builder.add(event)
        self.events.append(event)
        return bool(increment.factors)

    def feed(
        self, number: int, entry: dict[str, Any], streams: dict[str, RobotStream]
    ) -> list[Event]:
        """Turn dataset event ``number`` into estimator events; returns the new ones."""
        before = len(self.events)
        kind = entry["event"]
        if kind == "move":
            self._move(entry)
        elif kind == "dwell":
            self._dwell(number, entry, streams)
        return self.events[before:]

    def _move(self, entry: dict[str, Any]) -> None:
        robot = entry["robot"]
        stamps, poses = self.odometry[robot]
        start_s, end_s = float(entry["start_s"]), float(entry["t_s"])
        held = self._yaw.get(robot)
        if held is None or held[0] is not poses:  # the odometry grew (a live mission)
            held = self._yaw[robot] = (poses, np.unwrap(poses[:, 2]))
        before = pose_at(stamps, poses, start_s, held[1])
        after = pose_at(stamps, poses, end_s, held[1])
        self.odometry_at.setdefault((robot, int(entry["from_index"])), before)
        self.odometry_at[robot, int(entry["to_index"])] = after
        dx, dy, dyaw = (float(v) for v in se2.between(before, after))
        step = Move(robot, int(entry["to_index"]), (dx, dy, dyaw),
                    _motion(stamps, poses, start_s, end_s, before, after))  # fmt: skip
        if pose_key(robot, int(entry["from_index"])) in self.builder.guesses:
            self._emit(step)
        else:
            self.held_back += 1
            self.pending.setdefault(robot, []).append(step)

    def _dwell(self, number: int, entry: dict[str, Any], streams: dict[str, RobotStream]) -> None:
        config, builder = self.config, self.builder
        self.dwells += 1
        in_dwell: dict[str, Sweep] = {}
        for robot in self.robots:
            scan, why = streams[robot].sweep_of(number, entry, config)
            index = int(entry["poses"][robot])
            if scan is None:
                self.missing.append(f"{robot}{index} (dwell {number}): {why}")
                continue
            detections = streams[robot].dwell_beacons.get(number)
            if detections is None:  # not found when the sweep was made
                detections, _ = detect_beacons(scan.points_scanner, scan.reflector, **self.params)
            sweep = Sweep(robot, index, number, scan.points_scanner, detections)
            self.sweeps.append(sweep)
            in_dwell[robot] = sweep
        reference, mapper = entry.get("reference"), entry.get("mapper")
        if reference in in_dwell and mapper in in_dwell:
            ka = pose_key(reference, in_dwell[reference].index)
            kc = pose_key(mapper, in_dwell[mapper].index)
            # The other robots' beacons where the estimate places them: a third robot between
            # or beside the two shows its beacon too (generated building 103: a's sweeps took
            # c's beacon, 2.6 m off, for b's, 5 m off, at six stations in a row).
            third = [pose_key(r, int(i)) for r, i in entry["poses"].items()
                     if r not in (reference, mapper)]  # fmt: skip
            to_c, to_a = _predict(builder, ka, kc, config), _predict(builder, kc, ka, config)
            of_a = self._not_static(reference, mapper, entry["poses"], in_dwell[reference])
            of_c = self._not_static(mapper, reference, entry["poses"], in_dwell[mapper])
            seen_a, seen_c = _pair(
                _not_held(of_a, ka, third, self.held, builder.settings),
                _not_held(of_c, kc, third, self.held, builder.settings),
                None if to_c is None or to_a is None else (to_c, to_a), builder.settings,
                ([_predict(builder, ka, k, config) for k in third],
                 [_predict(builder, kc, k, config) for k in third]),
                [s.detections for r, s in in_dwell.items() if r not in (reference, mapper)],
            )  # fmt: skip
            if seen_a is None or seen_c is None:
                self.unseen.append(
                    f"{reference}{in_dwell[reference].index}–{mapper}{in_dwell[mapper].index}"
                )
            elif ka in builder.guesses or kc in builder.guesses:
                observer = (reference, in_dwell[reference].index)
                observed = (mapper, in_dwell[mapper].index)
                if self._emit(
                    Observe(
                        observer, observed,
                        seen_a.range_m, seen_a.bearing_rad, seen_c.range_m, seen_c.bearing_rad,
                    )
                ):  # fmt: skip
                    self.held[ka, kc] = (seen_a.range_m, seen_a.bearing_rad)
                    self.held[kc, ka] = (seen_c.range_m, seen_c.bearing_rad)
                self.observations += 1
                _flush_pending(self.pending, builder, self._emit)
        for robot, sweep in in_dwell.items():
            poses = {r: int(i) for r, i in entry["poses"].items()}
            self.last[robot] = (sweep.index, sweep.detections, poses)

    def _not_static(
        self, observer: str, partner: str, poses: dict[str, Any], sweep: Sweep
    ) -> list[BeaconDetection]:
        """The observer's detections without those it saw in its last sweep as well, from the
        same pose, while the partner's beacon has moved since by ``_MOVED_M`` or more (its
        odometry says): the partner's beacon cannot be where it was, so such a detection is
        something that stands still — a reflective sign, or a third robot that has not moved.
        Generated building 103, three robots: b's sweeps from b50 held a sign 2.18 m away in
        both dwells while c drove 4.9 m between them, and the sign passed the distance gate
        as c's beacon (the estimate, after a drive its odometry knew to 25 cm, placed c's
        beacon 3.1 m from where it stood): the rest of the mission was 16° off."""
        if observer not in self.last:
            return sweep.detections
        index, before, then = self.last[observer]
        partner_then, partner_now = then.get(partner), int(poses[partner])
        if index != sweep.index or partner_then is None or partner_then == partner_now:
            return sweep.detections
        was = self.odometry_at.get((partner, partner_then))
        now = self.odometry_at.get((partner, partner_now))
        if was is None or now is None:
            return sweep.detections
        beacon = np.array([self.config.robot.scanner_x_m + self.config.beacon.offset_m, 0.0])
        moved = np.linalg.norm(se2.transform_points(now, beacon[None])[0]
                               - se2.transform_points(was, beacon[None])[0])  # fmt: skip
        if moved < _MOVED_M:
            return sweep.detections
        where = [(d.range_m, d.bearing_rad) for d in before]
        return [d for d in sweep.detections
                if not _seen_at(d, where, self.builder.settings)]  # fmt: skip

    def counts(self) -> Counts:
        return Counts(self.dwells, self.observations, tuple(self.missing), tuple(self.unseen),
                      self.held_back)  # fmt: skip

    def result(self) -> EventStream:
        return EventStream(self.events, self.sweeps, self.counts(), self.builder)


def build_events(
    dataset: Dataset,
    streams: dict[str, RobotStream],
    progress: Progress | None = None,
) -> EventStream:
    """The estimator's event stream of a dataset, the sweeps, and the counts of what failed
    (:class:`EventMaker` over the dataset's event log)."""
    odometry = {r: dataset.odometry(r) for r in dataset.robots}
    maker = EventMaker(dataset.config, dataset.robots, dataset.starts, odometry)
    for number, entry in enumerate(dataset.events):
        maker.feed(number, entry, streams)
        if progress is not None:
            progress(f"event {number + 1}/{len(dataset.events)}")
    return maker.result()


def _third(
    detection: BeaconDetection,
    predicted: tuple[float, float] | None,
    others: Sequence[tuple[float, float] | None],
) -> bool:
    """Whether the estimate places the beacon of a robot not party to the observation
    (``others``: range, bearing; None where it places none) nearer ``detection`` than the
    partner's (``predicted``)."""
    if predicted is None:
        return False
    return any(o is not None and _apart(detection, o) < _apart(detection, predicted)
               for o in others)  # fmt: skip


def _placed(
    detection: BeaconDetection,
    predicted: tuple[float, float],
    others: Sequence[tuple[float, float] | None],
) -> bool:
    """Whether the estimate places a third robot's beacon at ``detection`` (within
    ``_THIRD_NEAR_M``) and the partner's far from it (``_PARTNER_FAR_M``): the detection is that
    robot's beacon, even with no sweep of it to claim it. Generated building 108, three robots:
    a's detection 3.311 m / −44.5° lay 6 mm from where the estimate put b's beacon and 2.4 m
    from c's; b's sweep did not see a, and the pair with c's detection of a was taken, 0.32 m
    and 47° off. A drifted estimate (half a metre, 16° after an untied turn) places no third
    beacon within a few centimetres of a detection by chance."""
    return _apart(detection, predicted) >= _PARTNER_FAR_M and any(
        o is not None and _apart(detection, o) <= _THIRD_NEAR_M for o in others
    )


def _not_held(
    seen: list[BeaconDetection],
    key: int,
    thirds: list[int],
    held: dict[tuple[int, int], tuple[float, float]],
    s: GraphSettings,
) -> list[BeaconDetection]:
    """``seen`` (the detections of the robot at pose ``key``) without those where it saw the
    beacon of a third robot (pose keys ``thirds``) in an accepted mutual observation while
    neither has moved since (``held``): that beacon stands there still, and a detection is one
    robot's beacon only. Generated building 100, three robots: a and c stood still after their
    observation; b came to stand as far from a on a's other side, and a's detection of c's
    beacon, which b's of a's agreed with as well, was taken for b's (2.17 m, 55° off)."""
    where = [held[key, t] for t in thirds if (key, t) in held]
    if not where:
        return seen
    return [d for d in seen if not _seen_at(d, where, s)]


def _seen_at(
    detection: BeaconDetection, where: Sequence[tuple[float, float]], s: GraphSettings
) -> bool:
    """Whether ``detection`` is, within the noise of two detections, one of the detections
    ``where`` (range, bearing) made from the same pose."""
    limit = _SIGHTING_CHI2 / 2  # two detections' noise: variances add
    return any(
        ((detection.range_m - r) / s.range_sigma_m) ** 2
        + (math.remainder(detection.bearing_rad - b, 2 * math.pi) / s.bearing_sigma_rad) ** 2
        <= limit
        for r, b in where
    )


def _apart(detection: BeaconDetection, where: tuple[float, float]) -> float:
    """How far a detection lies from a predicted beacon (range, and bearing times range)."""
    a, alpha = where
    return math.hypot(
        detection.range_m - a, a * math.remainder(detection.bearing_rad - alpha, 2 * math.pi)
    )


def _pair(
    seen_a: list[BeaconDetection],
    seen_c: list[BeaconDetection],
    predicted: tuple[tuple[float, float], tuple[float, float]] | None,
    settings: GraphSettings,
    others: tuple[list[tuple[float, float] | None], list[tuple[float, float] | None]] = ([], []),
    thirds: Sequence[list[BeaconDetection]] = (),
) -> tuple[BeaconDetection | None, BeaconDetection | None]:
    """The two robots' detections of each other's beacon (A's of C's, C's of A's), or Nones.

    Both measure the distance between the beacons (s1, s2: the graph's gate), so pairs that
    agree within the gate come first: a third robot's beacon or a reflective sign seldom lies
    at the distance the other robot measures. Then the pairs of which no detection lies nearer
    a third robot's beacon than the partner's, as the estimate so far places them (``others``:
    for A, then for C, range and bearing of each robot's beacon not party to the observation,
    None where it places none): an estimate that has drifted (half a metre, 16° after an
    untied turn) must not rule out the beacon that agrees. Then the pair nearest where the
    estimate places the partners' beacons (``predicted``: range and bearing of C's beacon from
    A, of A's from C), or without an estimate the best agreeing, then the best fitted. With
    no agreeing pair the nearest predicted one is taken, and the gate refuses it (generated
    building 103, three robots: c's beacon, 2.6 m from a, taken for b's, 5 m off, at six
    scan poses in a row; building 104: three robots placed side by side never tied a to b).

    A detection is a third robot's beacon beyond doubt when that robot's own sweep of the
    dwell (``thirds``: each third robot's detections) agrees with it as well, and the
    estimate places its beacon nearer than the partner's: no pair holding one is taken
    (building 101, three robots: a's sweep held c's beacon 2.643 m away and b's held a's
    2.666 m away, and the pair, 182 cm and 46° off, passed every gate).

    Before all of these but agreement, a pair that closes a triangle with a third robot comes
    first (and a detection that closure tests is no longer counted as the third's beacon): the
    third's sweep and the two robots' other detections give the A–T and T–C
    relative poses, and through T they place C where the pair does (:func:`_closing`). Only
    that tells the assignments apart when the three stand nearly symmetric (building 106: b
    saw a's beacon 2.29 m away and c's 2.25 m away, 16° apart, c saw b's 2.29 m away; every
    pairing agreed, and the estimate, after 167 untied turns, picked a's for c's, 73 cm off).
    Where a detection is missing for a whole triangle, a pair whose one observation with T
    places a one-way sighting that a sweep holds comes next (building 106, dwell 1053)."""
    if not seen_a or not seen_c:
        return None, None
    s = settings
    closing = _closing(seen_a, seen_c, thirds, s)
    rows = []
    for i, a in enumerate(seen_a):
        for j, c in enumerate(seen_c):
            gap, spread = _gap(a, c, s)
            agree = gap <= s.gate_sigmas * spread
            closes = closing.get((i, j), _Closes(0, False, False))
            if predicted is None:
                third, near, taken = False, gap, False
            else:
                third_a, third_c = (
                    _third(a, predicted[0], others[0]),
                    _third(c, predicted[1], others[1]),
                )
                third = third_a or third_c
                near = _apart(a, predicted[0]) + _apart(c, predicted[1])
                taken_a = (third_a and _claimed(a, thirds, s)) or _placed(
                    a, predicted[0], others[0]
                )
                taken_c = (third_c and _claimed(c, thirds, s)) or _placed(
                    c, predicted[1], others[1]
                )
                # A closure clears only the detections it tests (:class:`_Closes`).
                taken = (taken_a and not closes.a) or (taken_c and not closes.c)
            rows.append((not agree, -closes.level, taken, third, near,
                         -(a.quality + c.quality), i, j))  # fmt: skip
    best = min(rows)
    if best[2]:
        return None, None
    *_, i, j = best
    return seen_a[i], seen_c[j]


def _z(first: BeaconDetection, second: BeaconDetection) -> tuple[float, float, float, float]:
    """A mutual observation's four numbers: ``first`` sees the other's beacon, ``second`` the
    first's."""
    return (first.range_m, first.bearing_rad, second.range_m, second.bearing_rad)


class _Closes(NamedTuple):
    """How a pair of detections (A's of C's beacon, C's of A's) closes with a third robot: the
    level (2 a whole triangle, 1 a one-way sighting), and whether that closure tests A's
    detection (``a``) and C's (``c``). A third robot's sighting of A's beacon, placed through
    its observation with C, tests C's detection of A's beacon and not A's bearing to C's: A's
    heading is free in it (generated building 402, three robots standing 2.2 m apart: a saw
    only b's beacon, and the pair with c's true detection of a passed through b's sighting of
    a's beacon, 35 cm and 61° off)."""

    level: int
    a: bool
    c: bool


def _closing(
    seen_a: list[BeaconDetection],
    seen_c: list[BeaconDetection],
    thirds: Sequence[list[BeaconDetection]],
    s: GraphSettings,
) -> dict[tuple[int, int], _Closes]:
    """How well each pair (i, j) of A's and C's detections (A's of C's beacon, C's of A's)
    closes a triangle with a third robot T: 2 when a whole triangle closes (A's other detection
    i' and T's k agree as A–T's mutual observation, C's other j' and T's other k' as T–C's, and
    C's pose through T matches the pair's: :func:`~estimation.posegraph.mutual.closure_distance`,
    99.9 %); 1 when one mutual observation with T and the pair place a one-way sighting that a
    third sweep holds (:func:`~estimation.posegraph.mutual.sighting_distance`, 99.9 %: T's
    beacon where the robot not in that observation saw it, or its beacon where T saw it), with
    the detections each closure tests (:class:`_Closes`). Pairs that close nothing are left
    out."""
    out: dict[tuple[int, int], _Closes] = {}
    d, sr, sb = s.beacon_offset_m, s.range_sigma_m, s.bearing_sigma_rad
    pairs = list(itertools.product(range(len(seen_a)), range(len(seen_c))))
    for seen_t in thirds:
        at = [(i, k) for i, a in enumerate(seen_a) for k, t in enumerate(seen_t)
              if _agree(a, t, s)]  # fmt: skip
        tc = [(k, j) for k, t in enumerate(seen_t) for j, c in enumerate(seen_c)
              if _agree(t, c, s)]  # fmt: skip
        whole = [(i, j, i2, k, k2, j2) for i, j in pairs for i2, k in at if i2 != i
                 for k2, j2 in tc if k2 != k and j2 != j]  # fmt: skip
        if whole and len(whole) <= _CLOSURE_MAX:
            z_ac = np.array([_z(seen_a[i], seen_c[j]) for i, j, *_ in whole])
            z_at = np.array([_z(seen_a[i2], seen_t[k]) for _, _, i2, k, _, _ in whole])
            z_tc = np.array([_z(seen_t[k2], seen_c[j2]) for *_, k2, j2 in whole])
            d2 = closure_distance(z_ac, z_at, z_tc, d, sr, sb)
            for (i, j, *_), value in zip(whole, d2, strict=True):
                if value <= _CLOSURE_CHI2:
                    out[i, j] = _Closes(2, True, True)
        # One observation with T, and a sighting of or by the robot not in it.
        one: list[tuple[int, int, tuple[float, ...], tuple[float, float], str, int]] = []
        sides = (("A", [(i2, k, _z(seen_a[i2], seen_t[k])) for i2, k in at], seen_c),
                 ("C", [(j2, k, _z(seen_c[j2], seen_t[k])) for k, j2 in tc], seen_a))  # fmt: skip
        for i, j in pairs:
            for through, observations, seen_x in sides:
                # The pair's detection by the robot in the observation, and by the other one.
                own, other = (i, j) if through == "A" else (j, i)
                for mine, k, zp in observations:
                    if mine == own:
                        continue
                    one += [(i, j, zp, (x.range_m, x.bearing_rad), through, 0)
                            for n, x in enumerate(seen_x) if n != other]  # fmt: skip
                    one += [(i, j, zp, (t.range_m, t.bearing_rad), through, 1)
                            for n, t in enumerate(seen_t) if n != k]  # fmt: skip
        if not one or len(one) > _CLOSURE_MAX:
            continue
        for through, observer in (("A", 0), ("A", 1), ("C", 0), ("C", 1)):
            rows = [r for r in one if r[4] == through and r[5] == observer]
            if not rows:
                continue
            d2 = sighting_distance(
                np.array([_z(seen_a[r[0]], seen_c[r[1]]) for r in rows]),
                np.array([r[2] for r in rows]), np.array([r[3] for r in rows]),
                through, observer, d, sr, sb,  # type: ignore[arg-type]
            )  # fmt: skip
            # T's sighting of X's beacon tests only the detection of X's beacon in the pair
            # (made by the robot T observed with); X's sighting of T's beacon tests both.
            tests_a, tests_c = observer == 0 or through == "A", observer == 0 or through == "C"
            for r, value in zip(rows, d2, strict=True):
                if value <= _SIGHTING_CHI2:
                    was = out.get((r[0], r[1]), _Closes(0, False, False))
                    out[r[0], r[1]] = _Closes(max(was.level, 1), was.a or tests_a,
                                              was.c or tests_c)  # fmt: skip
    return out


def _gap(a: BeaconDetection, c: BeaconDetection, s: GraphSettings) -> tuple[float, float]:
    """|s1 − s2| of two detections taken as a mutual observation, and its predicted spread."""
    z = (a.range_m, a.bearing_rad, c.range_m, c.bearing_rad)
    s1, s2 = separations(*z, s.beacon_offset_m)
    spread = gap_sigma(*z, s.beacon_offset_m, s.range_sigma_m, s.bearing_sigma_rad)
    return abs(float(s1) - float(s2)), float(spread)


def _agree(a: BeaconDetection, c: BeaconDetection, s: GraphSettings) -> bool:
    """Whether two detections measure the same distance between the beacons (the s1/s2 gate)."""
    gap, spread = _gap(a, c, s)
    return gap <= s.gate_sigmas * spread


def _claimed(
    detection: BeaconDetection, thirds: Sequence[list[BeaconDetection]], s: GraphSettings
) -> bool:
    """Whether a third robot's sweep holds a detection that agrees with ``detection`` as the
    two robots' mutual observation (it measures the same distance between them)."""
    return any(_agree(detection, e, s) for seen in thirds for e in seen)


def _predict(
    builder: GraphBuilder, observer: int, observed: int, config: Config
) -> tuple[float, float] | None:
    """Range and bearing, in the observer's scanner frame, of the observed robot's beacon as the
    estimate so far places them (in the plane: heights do not enter range and bearing)."""
    guesses = builder.guesses
    if observer not in guesses or observed not in guesses:
        return None
    T_a = pose2_matrix(*guesses[observer]) @ T_robot_scanner(config, planar=True)
    beacon = pose2_matrix(*guesses[observed]) @ np.array(
        [config.robot.scanner_x_m + config.beacon.offset_m, 0, 0, 1]
    )
    local = np.linalg.inv(T_a) @ beacon
    return float(math.hypot(local[0], local[1])), float(math.atan2(local[1], local[0]))


def _motion(stamps: np.ndarray, poses: np.ndarray, start_s: float, end_s: float,
            before: np.ndarray, after: np.ndarray) -> tuple[float, float]:  # fmt: skip
    """How far the odometry says the robot drove and how much it turned between two instants
    (the samples in between, and the poses at both ends)."""
    inside = (stamps > start_s) & (stamps < end_s)
    track = np.vstack([before, poses[inside], after])
    driven = float(np.hypot(*np.diff(track[:, :2], axis=0).T).sum())
    turned = float(np.abs(np.angle(np.exp(1j * np.diff(track[:, 2])))).sum())
    return driven, turned


def _flush_pending(
    pending: dict[str, list[Move]],
    builder: GraphBuilder,
    emit: Callable[[Event], object],
) -> None:
    """Odometry of a robot that moved before its first fix joins once it is anchored."""
    for robot, moves in list(pending.items()):
        while moves and pose_key(robot, moves[0].index - 1) in builder.guesses:
            step = moves.pop(0)
            if pose_key(robot, step.index) not in builder.guesses:
                emit(step)
        if not moves:
            del pending[robot]
