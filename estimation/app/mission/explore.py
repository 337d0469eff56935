"""Next best views on the estimated map: where the leapfrog goes next (docs/design.md §13).

Everything here reads the occupancy grid as estimated, never the true world, through a
:class:`~estimation.app.mission.view.MapView` of it.

The explorer keeps the leapfrog of the paper: the reference turns in place to the heading from
which it and a mapper around it see the most unknown space on the way to the nearest reachable
frontier; the mapper then takes the scan poses, in the reference's front sectors and facing it
so that both beacons are in view, that add the most unknown space and bring the pair closer to
that frontier, less a cost for the path. A frontier no path reaches (floor glimpsed through a
doorway) is approached as the drivable floor from which it is in sight. Poses already taken
are not taken again; a frontier the pair has failed to shrink from several stations in a row
is given up. Once no frontier is left, the pair goes into the rooms of the estimated map that no
robot stood in (a room seen whole through its doors has no frontier), nearest first, as it would
to a frontier.

A turn in place is measured only by odometry unless a mutual observation ties it, and the
beacons see each other only between 15° and 45° off each robot's heading. So every turn is
planned as a :class:`TurnPlan`: in parts of at most ``_PART_RAD``, and before each part the
mapper drives to a pivot from which the reference sees its beacon both before and after that
part (or it already stands at one). The dwell at the pivot ties it to the reference before the
part, the station dwell after the part ties the turned reference to it: the chain of stations
never rests on a turn that odometry alone measured. Each pivot costs ``_PIVOT_COST`` in the
choice of heading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from estimation.app.config import Config
from estimation.app.mission.view import MIN_UNKNOWN_M2, MapView
from estimation.app.sim.planning import mapper_candidates
from mapping.traversability import Frontier, Room, frontiers

__all__ = ["Explorer", "ScanGoal", "StallWatch", "TurnPlan"]

#: Weights of a mapper pose's score, in floor cells: per metre of path driven, per metre still
#: to go to the target frontier.
_PATH_COST = 20.0
_FRONTIER_COST = 200.0
#: A heading facing at least this much unexplored floor (cells) may be taken before any mapper
#: pose there is known, at this cost (cells).
_LOOK_FIRST_CELLS, _LOOK_FIRST_COST = 200, 300.0
#: Two poses closer than this (m, rad) are the same pose.
_SAME_M, _SAME_RAD = 0.3, math.radians(30.0)
#: A scan pose is not planned where another robot stands this close (beyond its footprint) to
#: the line between the beacons; a robot this close to a pose is the robot standing there.
_BESIDE_M, _SAME_ROBOT_M = 0.3, 0.1
#: A frontier is given up after this many stations in a row that neither brought the robots
#: this much nearer nor grew the known floor within this radius of it by this much.
_PATIENCE = 3
_PROGRESS_M, _PROGRESS_M2, _PROGRESS_RADIUS_M = 0.3, 0.5, 3.0
#: A frontier whose centroid lies this close to the tracked target's is that target (frontiers
#: move and change shape as the map grows).
_SAME_TARGET_M = 1.5
#: A frontier counts when it has this many cells and borders at least ``MIN_UNKNOWN_M2`` of
#: unknown floor (a doorway onto a room nobody has seen, not the shadow of a desk).
_MIN_FRONTIER_CELLS = 5
#: A frontier the robots cannot drive to (floor seen through a doorway at a glancing angle: a
#: sliver of free floor, drivable only in a patch cut off from the doorway by what nobody saw)
#: is looked at from the drivable floor within this distance (m) of it, over known free floor.
_LOOK_M = 2.0
#: A turn is tied in parts of at most this much (a pivot pose must lie 15–45° off the heading
#: before and after its part), in at most this many parts; each pivot the mapper drives to costs
#: this much (cells) when the heading is chosen (a move and a dwell of some 35 s).
_PART_RAD = math.radians(75.0)
_MAX_PARTS = 3
_PIVOT_COST = 200.0
#: An untied turn costs this much (cells): as much as two pivots.
_UNTIED_COST = 400.0


#: Exploration stalls when the known floor grew by less than this (m²) over this many stations;
#: it goes on at a frontier never tried if one is left, and ends if none is: what frontiers are
#: left cannot be resolved from the floor the robots can reach.
_STALL_M2, _STALL_STATIONS = 2.0, 10


@dataclass
class StallWatch:
    """The known floor (m²) after each station since the window last restarted: exploring has
    stalled when it grew by less than ``_STALL_M2`` over ``_STALL_STATIONS`` stations. A station
    that brought the pair nearer to its target restarts the window: on the way to a far
    frontier no floor is added (generated building 17 ended so, 18 m short of the corridor
    left to explore, at 57 % of its floor)."""

    known: list[float] = field(default_factory=list)

    def add(self, known_m2: float, nearer: bool) -> bool:
        """Count a station; whether exploring has stalled."""
        self.known.append(known_m2)
        if nearer:
            self.restart()
        return len(self.known) > _STALL_STATIONS and (
            self.known[-1] - self.known[-1 - _STALL_STATIONS] < _STALL_M2
        )

    def restart(self) -> None:
        self.known = self.known[-1:]

    @staticmethod
    def why() -> str:
        return f"the known floor grew by less than {_STALL_M2:g} m² over {_STALL_STATIONS} stations"


#: Where the pair goes next: a frontier, or a room nobody stood in.
Target = Frontier | Room


@dataclass(frozen=True)
class ScanGoal:
    """A pose for a robot to drive to, the path there (map frame), and why it was chosen."""

    pose: np.ndarray  # (3,) x_m, y_m, yaw_rad
    path: list[np.ndarray]
    score: float


#: A part of a turn: the heading after it, and the pivot the mapper drives to before it.
_Part = tuple[float, "ScanGoal | None"]


@dataclass(frozen=True)
class TurnPlan:
    """The reference's turn to ``heading``: ``parts`` (heading after the part, the pivot the
    mapper drives to before it, None if it already stands where the reference sees it before
    and after). ``tied`` False: no chain of pivots was found; the turn is a single untied part."""

    heading: float
    parts: tuple[_Part, ...]
    tied: bool

    @property
    def pivots(self) -> int:
        return sum(1 for _, pivot in self.parts if pivot is not None)


@dataclass
class _Target:
    centroid: np.ndarray
    best_m: float
    known_m2: float
    stale: int = 0


def _reachable_targets(view: MapView, from_xy: list[np.ndarray],
                       given_up: list[np.ndarray]) -> list[tuple[Target, float]]:  # fmt: skip
    """The frontiers reachable from any of ``from_xy``, each with its path distance (m), and
    those no path reaches as the floor they are looked at from (:func:`_looked_at`); when each
    of them is among ``given_up`` (or none is left), the unvisited rooms too."""
    starts = [p for p in (view.free_near(xy) for xy in from_xy) if p is not None]
    if not starts:
        return []
    reach = view.distances_from(starts)
    found = frontiers(
        view.floor, view.space, robot_radius_m=view.radius_m,
        min_cells=_MIN_FRONTIER_CELLS, min_unknown_m2=MIN_UNKNOWN_M2,
    )  # fmt: skip
    out: list[tuple[Target, float]] = []
    for frontier in found:
        target: Target = frontier
        d = float(np.min(reach[frontier.cells[:, 0], frontier.cells[:, 1]]))
        if not np.isfinite(d):
            looked = _looked_at(view, frontier, reach)
            if looked is None:
                continue
            target, d = looked, float(np.min(reach[looked.cells[:, 0], looked.cells[:, 1]]))
        out.append((target, d))
    if all(_among(target, given_up) for target, _ in out):
        for room in view.rooms():
            d = float(np.min(reach[room.cells[:, 0], room.cells[:, 1]]))
            if np.isfinite(d):
                out.append((room, d))
    return out


def _looked_at(view: MapView, frontier: Frontier, reach: np.ndarray) -> Frontier | None:
    """A frontier no path reaches, as the reachable drivable cells (finite ``reach``) within
    ``_LOOK_M`` of it from which its nearest cell is in sight over known free floor (centroid and
    size its own); None without such a cell.

    Generated building 10 stalled with two rooms unentered: the one room behind the other's
    door had been seen only through that door at a glancing angle from the corridor, a sliver of
    free floor whose drivable patch was cut off from the doorway by unseen floor. No path led to
    its frontier, so it was never a target, though a look from the doorway shows the room."""
    floor, res = view.floor, view.floor.resolution_m
    h, w = floor.shape
    k = math.ceil(_LOOK_M / res)
    r0, c0 = np.maximum(frontier.cells.min(axis=0) - k, 0)
    r1, c1 = np.minimum(frontier.cells.max(axis=0) + k + 1, (h, w))
    away = np.ones((r1 - r0, c1 - c0), dtype=bool)
    away[frontier.cells[:, 0] - r0, frontier.cells[:, 1] - c0] = False
    distance, (rows, cols) = ndimage.distance_transform_edt(away, return_indices=True)
    near = np.isfinite(reach[r0:r1, c0:c1]) & (distance * res <= _LOOK_M)
    if not near.any():
        return None
    start = np.argwhere(near).astype(float)
    end = np.column_stack([rows[near], cols[near]]).astype(float)
    t = np.linspace(0.0, 1.0, 2 * k + 1)[None, :, None]
    line = np.rint(start[:, None, :] + t * (end - start)[:, None, :]).astype(np.int64)
    seen = floor.free[r0:r1, c0:c1][line[..., 0], line[..., 1]].all(axis=1)
    if not seen.any():
        return None
    cells = start[seen].astype(np.int64) + np.array([r0, c0])
    return Frontier(cells, frontier.centroid_xy, frontier.size)


def _in_the_way(a: np.ndarray, b: np.ndarray, robots: list[np.ndarray],
                radius_m: float) -> bool:  # fmt: skip
    """Whether a robot other than the one at ``a`` stands within ``radius_m`` plus
    ``_BESIDE_M`` of the line from ``a`` to ``b``: its body hides the beacon, or its own beacon
    beside the line is taken for it (generated building 103: c stood between a and b for six
    scan poses in a row, and a's sweeps showed c's beacon)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    d = b - a
    length2 = float(d @ d)
    for robot in robots:
        p = np.asarray(robot[:2], dtype=float)
        if math.dist(p, a) < _SAME_ROBOT_M:
            continue  # the robot at a itself
        t = 0.0 if length2 == 0.0 else float(np.clip((p - a) @ d / length2, 0.0, 1.0))
        if math.dist(p, a + t * d) < radius_m + _BESIDE_M:
            return True
    return False


def _among(frontier: Target, centroids: list[np.ndarray]) -> bool:
    """The frontier is one of those with these centroids (within 1 m: frontiers move)."""
    return any(math.dist(frontier.centroid_xy, c) < 1.0 for c in centroids)


def _known_near(view: MapView, xy: np.ndarray) -> float:
    """Known floor (m²) within ``_PROGRESS_RADIUS_M`` of ``xy``."""
    floor = view.floor
    res = floor.resolution_m
    rows, cols = np.indices(floor.shape)
    x = floor.lower_xy[0] + (cols + 0.5) * res
    y = floor.lower_xy[1] + (rows + 0.5) * res
    near = np.hypot(x - xy[0], y - xy[1]) <= _PROGRESS_RADIUS_M
    return float((near & ~floor.unknown).sum()) * res * res


@dataclass
class Explorer:
    """The leapfrog's choices on the estimated map (see the module's docstring)."""

    config: Config
    band: tuple[float, float]
    taken: list[np.ndarray] = field(default_factory=list)  # every pose any robot took
    given_up: list[np.ndarray] = field(default_factory=list)  # frontier centroids
    retried: list[np.ndarray] = field(default_factory=list)  # given up once, tried again
    target: _Target | None = None
    #: The corner of the floor map whose cells the target's count from: the map grows during
    #: a station, and with it the next view's corner (generated building 104, three robots:
    #: a frontier's cells indexed past the grown map's edge).
    frame_xy: np.ndarray | None = None
    _taken_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)

    def centres(self, view: MapView, target: Target) -> np.ndarray:
        """The centres (N, 2) of the target's cells in the map frame."""
        lower = view.floor.lower_xy if self.frame_xy is None else self.frame_xy
        return lower + (target.cells[:, ::-1] + 0.5) * view.floor.resolution_m

    def _taken(self, pose: np.ndarray) -> bool:
        # ``taken`` only grows: its places as one array, to find the few nearby at once.
        if len(self._taken_xy) != len(self.taken):
            self._taken_xy = np.array([p[:2] for p in self.taken], dtype=float).reshape(-1, 2)
        gap = self._taken_xy - np.asarray(pose[:2], dtype=float)
        near = np.flatnonzero(np.hypot(gap[:, 0], gap[:, 1]) < _SAME_M + 1e-9)
        return any(
            math.dist(pose[:2], p[:2]) < _SAME_M
            and abs(math.remainder(pose[2] - p[2], 2 * math.pi)) < _SAME_RAD
            for p in (self.taken[i] for i in near)
        )

    def frontier(self, view: MapView, from_xy: list[np.ndarray]) -> Target | None:
        """:meth:`_frontier`; its cells count from ``view``'s corner (``frame_xy``)."""
        found = self._frontier(view, from_xy)
        self.frame_xy = view.floor.lower_xy.copy()
        return found

    def _frontier(self, view: MapView, from_xy: list[np.ndarray]) -> Target | None:
        """The frontier the pair works on while it is still reachable and not given up (the
        tracked target); else the reachable frontier nearest (by path) to any of ``from_xy``,
        not given up. When only given-up frontiers are left, the nearest of them: the first
        time each is counted as retried (the map has grown since); after that the stall rule
        of the loop decides when exploring ends, not this one. The rooms nobody stood in count
        as frontiers once every frontier left was given up. None when no reachable frontier or
        unvisited room is left at all.

        Keeping the target matters: the two robots stand a few metres apart and swap roles at
        every station, and the frontier nearest to the pair flipped between two sides of a room
        from one station to the next (generated building 0: 8 stations zigzagging over 3 m).
        Never ending on given-up frontiers matters too: building 0 at 150 stations ended after
        29, with the doorway to the rest of the building given up twice."""
        target = self.target
        best, best_m = None, math.inf
        kept, kept_m = None, math.inf
        given_best, given_m = None, math.inf
        for frontier, d in _reachable_targets(view, from_xy, self.given_up):
            if _among(frontier, self.given_up):
                if d < given_m:
                    given_best, given_m = frontier, d
                continue
            if d < best_m:
                best, best_m = frontier, d
            if (
                target is not None
                and d < kept_m
                and math.dist(frontier.centroid_xy, target.centroid) <= _SAME_TARGET_M
            ):
                kept, kept_m = frontier, d
        if kept is not None:
            return kept
        if best is not None or given_best is None:
            return best
        if not self.retried:
            self.retried, self.given_up = list(self.given_up), []
        return given_best

    def abandon(self, view: MapView, from_xy: list[np.ndarray]) -> bool:
        """Exploration stalled: give up the target and say whether a reachable frontier is left
        that was never given up (the one :meth:`frontier` will then pick), or, when none is, a
        given-up one that was never tried again: then every given-up frontier is tried once
        more (:meth:`frontier` does so too, but only once no room nobody stood in is left;
        generated building 17 stalled on a room it could not enter while the frontier at a
        door it had given up early was never tried again)."""
        abandoned = []
        if self.target is not None:
            abandoned = [self.target.centroid.copy()]
            self.given_up += abandoned
            self.target = None
        tried = [*self.given_up, *self.retried]
        left = [f for f, _ in _reachable_targets(view, from_xy, tried)]
        if any(not _among(f, tried) for f in left):
            return True
        again = self.given_up[: len(self.given_up) - len(abandoned)]  # not the one just left
        if self.retried or not any(_among(f, again) for f in left):
            return False
        self.retried, self.given_up = again, abandoned
        return True

    def progress(self, frontier: Target | None, distance_m: float, view: MapView) -> bool:
        """Track the target frontier across stations; give it up when it stops yielding: the
        robots came no nearer (by ``_PROGRESS_M``) and the known floor around it grew by less
        than ``_PROGRESS_M2`` (a frontier that recedes as a room is mapped is progress).
        Returns whether the robots came nearer to the same target than ever before."""
        if frontier is None:
            self.target = None
            return False
        known = _known_near(view, frontier.centroid_xy)
        t = self.target
        if t is None or math.dist(t.centroid, frontier.centroid_xy) > _SAME_TARGET_M:
            self.target = _Target(frontier.centroid_xy.copy(), distance_m, known)
            return False
        # The floor known around where the target was at the last station, then and now: as a
        # corridor is mapped its frontier moves on, and less is known around the new place.
        moved = not np.array_equal(t.centroid, frontier.centroid_xy)
        before = _known_near(view, t.centroid) if moved else known
        nearer = distance_m < t.best_m - _PROGRESS_M
        if nearer or before >= t.known_m2 + _PROGRESS_M2:
            t.stale = 0
        else:
            t.stale += 1
        t.best_m, t.known_m2 = min(t.best_m, distance_m), known
        t.centroid = frontier.centroid_xy.copy()
        if t.stale >= _PATIENCE:
            self.given_up.append(t.centroid.copy())
            self.target = None
        return nearer

    def _goal_field(self, view: MapView, frontier: Target | None) -> np.ndarray:
        if frontier is None:
            return np.zeros(view.space.free.shape)
        return view.distances_from(list(self.centres(view, frontier)))

    def _candidates(self, view: MapView, reference: np.ndarray, mapper: np.ndarray,
                    others: list[np.ndarray], reachable: np.ndarray,
                    exclude: list[np.ndarray], fresh: bool = True) -> list[np.ndarray]:  # fmt: skip
        """Mapper poses around ``reference`` with both beacons in view, drivable and reachable,
        clear of the other robots; ``fresh``: not taken before."""
        spacing = 2 * self.config.robot.footprint_radius_m + 0.3
        out = []
        for candidate in mapper_candidates(reference, view.geometry, self.band):
            xy = candidate[:2]
            if not view.space.is_free(xy) or not np.isfinite(view.at(reachable, xy)):
                continue
            if any(math.dist(xy, p[:2]) < spacing for p in others):
                continue
            if _in_the_way(reference[:2], xy, others, self.config.robot.footprint_radius_m):
                continue
            if fresh and self._taken(candidate):
                continue
            if any(math.dist(xy, p[:2]) < _SAME_M for p in exclude):
                continue
            if not view.geometry.mutual(reference, candidate, self.band):
                continue
            out.append(candidate)
        return out

    def heading(self, view: MapView, reference: np.ndarray, mapper: np.ndarray,
                others: list[np.ndarray], frontier: Target | None,
                look_first: bool = False) -> TurnPlan | None:  # fmt: skip
        """The reference's turn for its next station, or None if from no heading a mapper pose
        around it would see its beacon. With ``look_first``, a heading facing enough unexplored
        floor counts even before a mapper pose there is known: the reference's own sweep at the
        station shows the floor the mapper will drive on. The heading with the best score less
        the cost of the pivots that tie the turn wins, unless the best heading (one to look
        first included), turned to untied, scores more than ``_UNTIED_COST`` above it. Untied,
        the turn is measured by the reference's odometry until the mapper, having driven by
        odometry from a tied pose, observes it, and by the station's link to the one before.
        Without untied turns the reference at the front of the pair, which faces its partner
        to see its beacon, kept facing back wherever no pivot fits (narrow rooms): the mapper
        then scanned behind it, and the pair advanced 0.7 m per station (generated building 0:
        12 stations up a 3.3 m wide office). With untied turns only where a mapper pose was
        known, a turn only to look stayed tied, and the same happened wherever nothing beyond
        the front robot had been seen yet (building 0: 20 stations across a 3.3 m × 4.8 m
        office; 5 once such a turn may be untied)."""
        start = view.free_near(mapper[:2])
        if start is None:
            return None
        reachable = view.distances_from([start])
        goal = self._goal_field(view, frontier)
        scored: list[tuple[float, float]] = []
        for heading in np.radians(np.arange(0.0, 360.0, 15.0)):
            pose = np.array([reference[0], reference[1], heading])
            candidates = self._candidates(view, pose, mapper, others, reachable, [])
            own = view.coverage.gain(pose)
            if candidates:
                values = [self._value(view, c, reachable, goal) for c in candidates[::2]]
                scored.append((max(values) + own, float(heading)))
            elif look_first and own >= _LOOK_FIRST_CELLS:
                scored.append((own - _LOOK_FIRST_COST, float(heading)))
        if not scored:
            return None
        scored.sort(key=lambda item: -item[0])  # stable: the first of equal scores stays first
        untied = scored[0]  # the best heading, were it turned to untied
        best: tuple[float, TurnPlan] | None = None
        for score, heading in scored:
            if best is not None and score <= best[0]:
                break  # the pivots only lower a score: no heading left can win
            parts = self.tie(view, reference, heading, mapper, others)
            if parts is None:
                continue
            plan = TurnPlan(heading, parts, True)
            value = score - _PIVOT_COST * plan.pivots
            if best is None or value > best[0]:
                best = (value, plan)
        if best is None or untied[0] - _UNTIED_COST > best[0]:
            return TurnPlan(untied[1], ((untied[1], None),), False)
        return best[1]

    def tie(self, view: MapView, reference: np.ndarray, heading: float, mapper: np.ndarray,
            others: list[np.ndarray]) -> tuple[_Part, ...] | None:  # fmt: skip
        """The parts of the reference's turn to ``heading`` with their pivots (see
        :class:`TurnPlan`), or None when some part has no pivot the mapper can reach."""
        tie_band = (0.5, self.config.beacon.max_range_m)
        turn = math.remainder(heading - reference[2], 2 * math.pi)
        count = max(1, math.ceil(abs(turn) / _PART_RAD - 1e-9))
        if count > _MAX_PARTS:
            return None
        parts: list[_Part] = []
        at, before = np.asarray(mapper, dtype=float), np.asarray(reference, dtype=float)
        for n in range(1, count + 1):
            after = np.array([reference[0], reference[1], reference[2] + turn * n / count])
            if n == count:
                after[2] = heading
            if view.geometry.mutual(after, at, tie_band):
                parts.append((float(after[2]), None))
            else:
                pivot = self.pivot(view, before, after, at, others)
                if pivot is None:
                    return None
                parts.append((float(after[2]), pivot))
                at = pivot.pose
            before = after
        return tuple(parts)

    def pivot(self, view: MapView, before: np.ndarray, after: np.ndarray, at: np.ndarray,
              others: list[np.ndarray],
              exclude: list[np.ndarray] | None = None) -> ScanGoal | None:  # fmt: skip
        """The nearest pose (by path from ``at``) from which the mapper sees the reference's
        beacon, and the reference its beacon, both at heading ``before`` and ``after``; not
        within 30 cm of ``exclude`` (pivots that failed)."""
        start = view.free_near(at[:2])
        if start is None:
            return None
        reachable = view.distances_from([start])
        candidates = [
            c
            for c in self._candidates(view, before, at, others, reachable, [], fresh=False)
            if view.geometry.mutual(after, c, self.band)
        ]
        for candidate in sorted(candidates, key=lambda c: view.at(reachable, c[:2]))[:6]:
            path = view.space.path(start, candidate[:2])
            if path is None:
                continue
            if math.dist(start, at[:2]) > 1e-6:
                path = [np.asarray(at[:2], dtype=float), *path]
            return ScanGoal(candidate, path, -_PATH_COST * view.at(reachable, candidate[:2]))
        return None

    def _value(self, view: MapView, candidate: np.ndarray, reachable: np.ndarray,
               goal: np.ndarray) -> float:  # fmt: skip
        to_goal = view.at(goal, candidate[:2])
        to_goal = to_goal if np.isfinite(to_goal) else 0.0
        return (
            view.coverage.gain(candidate)
            - _PATH_COST * view.at(reachable, candidate[:2])
            - _FRONTIER_COST * to_goal
        )

    def scan_pose(self, view: MapView, reference: np.ndarray, mapper: np.ndarray,
                  others: list[np.ndarray], frontier: Target | None,
                  exclude: list[np.ndarray]) -> ScanGoal | None:  # fmt: skip
        """The mapper's next scan pose around the reference and its path, or None."""
        start = view.free_near(mapper[:2])
        if start is None:
            return None
        reachable = view.distances_from([start])
        goal = self._goal_field(view, frontier)
        ranked = sorted(
            ((self._value(view, c, reachable, goal), k, c) for k, c in enumerate(
                self._candidates(view, reference, mapper, others, reachable, exclude))),
            key=lambda item: (-item[0], item[1]),
        )  # fmt: skip
        for score, _, candidate in ranked[:12]:
            path = view.space.path(start, candidate[:2])
            if path is None:
                continue
            if math.dist(start, mapper[:2]) > 1e-6:
                path = [np.asarray(mapper[:2], dtype=float), *path]
            return ScanGoal(candidate, path, float(score))
        return None
