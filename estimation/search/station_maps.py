"""Station maps inside a mission, built once and kept while their views stay put (docs/design.md
§6, §7).

A reference station's map is the ceiling band of the sweeps of its dwells taken at poses tied to
it by a mutual observation (:func:`tied_views`), fused in the station's robot frame from the rays
that reach the band's heights (:func:`band_slab`; the band is that of every ray). It depends
on the *relative* poses of those views to the station only, so when the estimate moves between
the search stages (the whole mission shifts by metres once the links fix its headings) the map
stays what it was. :class:`StationMaps` keeps each station's band and the relative poses it was
fused at, and fuses a station again only when one of its views moved relative to it by more than
``tolerance_m`` at any of its points (a bound: translation + rotation × the view's reach). With
``tolerance_m = 0`` a map is reused only when the relative poses are bit for bit the same, so
the bands equal those fused from scratch.

A loop closure matches a station against the map of the older stations near it, fused in the
frame of the nearest of them (the anchor). :meth:`StationMaps.older_band` keeps that 3D grid per
anchor and, when the next search of the same anchor asks for the same stations plus newer ones
(the views fused so far a prefix of the views wanted, their poses relative to the anchor within
the tolerance), fuses only the new views into it: fusion is sequential, so appending in order
gives the grid that fusing the whole list would. Any other change rebuilds the anchor's grid.
Which older stations it holds is chosen in :mod:`estimation.search.older_stations`.

Every fusion is counted per station (rays, seconds) in :attr:`StationMaps.work`, for the
benchmark of per-station work against mission length (``coopmap bench stations``).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from estimation.posegraph.graph import FactorSpec
from estimation.posegraph.keys import pose_key
from estimation.search.exhaustive import SearchParams
from estimation.search.registration import Cloud, RegistrationParams
from mapping.band import Band, CeilingRule, band_slab_m, extract_band, extract_ceiling_band
from mapping.errors import MapError
from mapping.fusion import Scan as MapScan
from mapping.fusion import fuse_scans, rays_into_slab
from mapping.grid import GridParams, OccupancyGrid
from sensors.geometry import se2
from sensors.geometry.frames import pose2_matrix

__all__ = [
    "Dwell",
    "Station",
    "StationMaps",
    "StationParams",
    "StationWork",
    "View",
    "band_of_grid",
    "band_slab",
    "cloud_of_views",
    "fuse_band",
    "fuse_views",
    "mutual_ties",
    "side_by_side",
    "tied_views",
]

_T = TypeVar("_T")
_R = TypeVar("_R")

#: A band with fewer known cells than this is no map to match (a station that saw no ceiling).
MIN_KNOWN_CELLS = 50
#: Grids of older stations kept (one per anchor, the most recently used): consecutive stations
#: mostly share their anchor; a long mission would otherwise hold one grid per station.
_OLDER_GRIDS = 4


@dataclass(frozen=True, eq=False)
class View:
    """One sweep a station map is fused from: the robot pose it was taken at, its points."""

    robot: str
    index: int
    points_scanner: np.ndarray  # (N, 3), scanner frame
    dwell: int = -1  # the mission's dwell (event number) it was taken in; -1: not known

    @property
    def key(self) -> int:
        return pose_key(self.robot, self.index)


@dataclass(frozen=True, eq=False)
class Station:
    """A reference robot's station: its pose, when its dwells began, the sweeps of its dwells."""

    robot: str
    index: int
    time_s: float
    views: tuple[View, ...]

    @property
    def key(self) -> int:
        return pose_key(self.robot, self.index)

    @property
    def label(self) -> str:
        return f"{self.robot}{self.index}"


@dataclass(frozen=True, eq=False)
class Dwell:
    """A dwell after the world changed: when it began and every robot's sweep in it."""

    time_s: float
    views: tuple[View, ...]


@dataclass(frozen=True, eq=False)
class StationParams:
    """What the station searches need: how to fuse a station map and cut its bands, and how to
    search. ``station_search`` differs from ``search`` in β only: station maps, each fused from a
    few views with millimetre relative poses, agree with each other more closely than a single
    view agrees with a whole map, so their PDF is sharper (the calibration is in the README).
    ``reuse_tolerance_m``: a station map is fused again when a view moved relative to its
    station by more than this at any of its points (0: only when the poses are bit-identical).
    ``registration``: how links and loop closures are refined on the stations' 3D points
    (None: the search's pose is the measurement)."""

    search: SearchParams  # relocalization against the whole map
    station_search: SearchParams  # links and loop closures
    grid: GridParams
    T_robot_scanner: np.ndarray  # (4, 4)
    ceiling_m: tuple[float, float]  # band limits above the floor
    floor_m: tuple[float, float]
    free_min_observed: float
    window_m: float  # relocalization's first window side, and its largest
    max_window_m: float
    ceiling_rule: CeilingRule | None = None  # a band that follows the ceiling, else ceiling_m
    reuse_tolerance_m: float = 0.0
    registration: RegistrationParams | None = None  # refine the searches' poses on the points


@dataclass
class StationWork:
    """The fusion work done for one station: rays cast and wall seconds, for its own map and
    for the older stations' map its loop closure searched."""

    own_rays: int = 0
    own_seconds: float = 0.0
    own_builds: int = 0
    older_rays: int = 0
    older_seconds: float = 0.0
    search_seconds: float = 0.0

    @property
    def rays(self) -> int:
        return self.own_rays + self.older_rays

    @property
    def seconds(self) -> float:
        return self.own_seconds + self.older_seconds + self.search_seconds


def mutual_ties(factors: Iterable[FactorSpec]) -> dict[int, set[int]]:
    """Every pose key → the keys a mutual observation ties it to (itself included)."""
    ties: dict[int, set[int]] = {}
    for factor in factors:
        if factor.kind == "mutual":
            for key in factor.keys:
                ties.setdefault(key, {key}).update(factor.keys)
    return ties


def tied_views(station: Station, ties: dict[int, set[int]]) -> list[View]:
    """The views of a station's dwells taken at poses tied to it by a mutual observation (its
    own and the mapper's around it): the others sit there only through odometry."""
    tied = ties.get(station.key, {station.key})
    return [v for v in station.views if v.key in tied]


def _T_frame_scanner(
    views: Sequence[View], frame: np.ndarray, estimate: dict[int, np.ndarray],
    params: StationParams,
) -> np.ndarray:  # fmt: skip
    """(k, 4, 4): each view's scanner frame in the robot frame ``frame`` (a map pose)."""
    T_frame_map = np.linalg.inv(pose2_matrix(*frame))
    return np.stack(
        [T_frame_map @ (pose2_matrix(*estimate[v.key]) @ params.T_robot_scanner) for v in views]
    ).reshape(-1, 4, 4)


def cloud_of_views(
    views: Sequence[View],
    frame: np.ndarray,
    estimate: dict[int, np.ndarray],
    params: StationParams,
    registration: RegistrationParams,
) -> Cloud:
    """The views' points in the robot frame ``frame``, as a registration :class:`Cloud` whose
    normals face the scanners that saw them."""
    transforms = _T_frame_scanner(views, frame, estimate, params)
    pairs = zip(views, transforms, strict=True)
    points = [v.points_scanner @ T[:3, :3].T + T[:3, 3] for v, T in pairs]
    if not points:
        return Cloud.empty()
    origins = [np.broadcast_to(T[:3, 3], p.shape) for p, T in zip(points, transforms, strict=True)]
    return Cloud.of(np.vstack(points), registration, viewpoints=np.vstack(origins))


def fuse_views(
    views: Sequence[View],
    frame: np.ndarray,
    estimate: dict[int, np.ndarray],
    params: StationParams,
    grid: OccupancyGrid | None = None,
    which: str | None = None,
) -> tuple[OccupancyGrid, int]:
    """The views fused, in order, into ``grid`` (a new one if None) in the robot frame ``frame``
    (a pose in the map frame); every view must have a pose in ``estimate``. With ``which``
    ("ceiling" or "floor"), only the rays that reach that band's heights (:func:`band_slab`):
    its cells are the same. Returns the grid and the rays cast."""
    transforms = _T_frame_scanner(views, frame, estimate, params)
    slab = band_slab(params, which) if which is not None else None
    scans = [MapScan(v.points_scanner if slab is None else v.points_scanner[  # heights only
        rays_into_slab(v.points_scanner @ T[2, :3] + T[2, 3], float(T[2, 3]), *slab)
    ]) for v, T in zip(views, transforms, strict=True)]  # fmt: skip
    grid = fuse_scans(scans, transforms, params.grid, grid)
    return grid, sum(len(scan.points_scanner) for scan in scans)


def band_slab(params: StationParams, which: str) -> tuple[float, float] | None:
    """The heights a ray must reach into to touch a cell of a station grid's ``which`` band
    (:func:`mapping.band.band_slab_m`); None when every ray counts: a band that follows the
    ceiling takes each column's highest occupied cell, wherever it lies."""
    if which == "ceiling" and params.ceiling_rule is not None:
        return None
    low, high = params.ceiling_m if which == "ceiling" else params.floor_m
    try:
        return band_slab_m(float(params.grid.origin_m[2]), params.grid.resolution_m, low, high)
    except MapError:
        return None  # no layer: the band is refused when cut


def band_of_grid(grid: OccupancyGrid, params: StationParams, which: str) -> Band | None:
    """The ceiling (or floor) band of a station grid, or None when it holds too little."""
    low, high = params.ceiling_m if which == "ceiling" else params.floor_m
    try:
        if which == "ceiling" and params.ceiling_rule is not None:
            band = extract_ceiling_band(grid, params.ceiling_rule,
                                        free_min_observed=params.free_min_observed)  # fmt: skip
        else:
            band = extract_band(grid, low, high, free_min_observed=params.free_min_observed)
    except MapError:
        return None
    return band if band.known.sum() > MIN_KNOWN_CELLS else None


def fuse_band(views: list[View], frame: np.ndarray, estimate: dict[int, np.ndarray],
              params: StationParams, which: str) -> Band | None:  # fmt: skip
    """The band of the views (those with a pose) fused in the robot frame ``frame``."""
    usable = [v for v in views if v.key in estimate]
    if not usable:
        return None
    return band_of_grid(fuse_views(usable, frame, estimate, params, which=which)[0], params, which)


def _relative(
    frame: np.ndarray, views: Sequence[View], estimate: dict[int, np.ndarray]
) -> np.ndarray:
    """(k, 3): each view's pose in the robot frame ``frame``."""
    if not views:
        return np.zeros((0, 3))
    poses = np.array([estimate[v.key] for v in views], dtype=np.float64)
    return np.asarray(se2.between(np.asarray(frame, dtype=np.float64), poses)).reshape(-1, 3)


def _reach(view: View, mount: np.ndarray) -> float:
    """How far from the robot origin (in the plane) the view's points lie, at most."""
    if len(view.points_scanner) == 0:
        return 0.0
    xy = view.points_scanner[:, :2] @ mount[:2, :2].T + mount[:2, 3]
    return float(np.sqrt((xy * xy).sum(axis=1).max()))


def _moved_m(before: np.ndarray, after: np.ndarray, reach_m: np.ndarray) -> float:
    """The largest displacement of any point (within ``reach_m`` of its view's origin) when the
    views' relative poses change from ``before`` to ``after`` ((k, 3) each)."""
    if len(before) == 0:
        return 0.0
    delta = np.asarray(se2.between(before, after)).reshape(-1, 3)
    shift = np.hypot(delta[:, 0], delta[:, 1]) + np.abs(delta[:, 2]) * reach_m
    return float(shift.max())


def side_by_side(work: Callable[[_T], _R], items: list[_T], workers: int) -> list[_R]:
    """``work`` of each item, in order; on up to ``workers`` threads when there are several."""
    if len(items) > 1 and workers > 1:
        with ThreadPoolExecutor(max_workers=min(workers, len(items))) as pool:
            return list(pool.map(work, items))
    return [work(item) for item in items]


@dataclass
class _OwnMap:
    views: tuple[int, ...]
    relative: np.ndarray  # (k, 3) the views' poses in the station's frame when fused
    band: Band | None
    cloud: Cloud | None = None  # made when a registration first asks for it
    rays: int = 0  # cast to fuse it


@dataclass
class _OlderMap:
    views: list[int]  # fused so far, in order
    relative: np.ndarray  # (k, 3) their poses in the anchor's frame when fused
    grid: OccupancyGrid
    band: Band | None = None
    banded: int = -1  # how many views the band was cut from


#: What one closure's older-stations band took: the band, the rays cast, the seconds.
_OlderMade = tuple[Band | None, int, float]
#: An anchor's key, its closures (their numbers in order) and its grid kept so far.
_OlderGroup = tuple[int, list[int], _OlderMap | None]


@dataclass
class StationMaps:
    """The station maps of a mission, built once and updated as the estimate moves (see the
    module's docstring). One instance serves every search stage of a run."""

    params: StationParams
    work: dict[int, StationWork] = field(default_factory=dict)
    _own: dict[int, _OwnMap] = field(default_factory=dict)
    _older: OrderedDict[int, _OlderMap] = field(default_factory=OrderedDict)
    _reach: dict[int, tuple[View, float]] = field(default_factory=dict)  # by id(view)

    def _work(self, key: int) -> StationWork:
        return self.work.setdefault(key, StationWork())

    def _reaches(self, views: Sequence[View]) -> np.ndarray:
        mount = self.params.T_robot_scanner
        for v in views:
            if id(v) not in self._reach:  # the view is held, so its id stays its own
                self._reach[id(v)] = (v, _reach(v, mount))
        return np.array([self._reach[id(v)][1] for v in views])

    def _still(self, before: np.ndarray, after: np.ndarray, views: Sequence[View]) -> bool:
        if self.params.reuse_tolerance_m <= 0.0:
            return bool(np.array_equal(before, after))
        return _moved_m(before, after, self._reaches(views)) <= self.params.reuse_tolerance_m

    def _own_map(
        self, station: Station, estimate: dict[int, np.ndarray], ties: dict[int, set[int]]
    ) -> tuple[_OwnMap, list[View]] | None:
        """The station's own map (its band fused again if a view moved), and its views."""
        wanted = self._own_wanted(station, estimate, ties)
        if wanted is None:
            return None
        kept, views, relative = wanted
        if kept is None:
            kept = self._keep_own(station, views, *self._fuse_own(station, views, relative,
                                                                  estimate))  # fmt: skip
        return kept, views

    def _own_wanted(
        self, station: Station, estimate: dict[int, np.ndarray], ties: dict[int, set[int]]
    ) -> tuple[_OwnMap | None, list[View], np.ndarray] | None:
        """The station's kept map if its views stayed put (else None), its views and their
        poses relative to it; None when it has no view with a pose."""
        views = [v for v in tied_views(station, ties) if v.key in estimate]
        if not views:
            return None
        relative = _relative(estimate[station.key], views, estimate)
        keys = tuple(v.key for v in views)
        kept = self._own.get(station.key)
        if kept is not None and kept.views == keys and self._still(kept.relative, relative, views):
            return kept, views, relative
        return None, views, relative

    def _fuse_own(
        self, station: Station, views: list[View], relative: np.ndarray,
        estimate: dict[int, np.ndarray],
    ) -> tuple[_OwnMap, float]:  # fmt: skip
        """The station's map fused afresh (touches nothing kept: runs on any thread), and the
        seconds it took."""
        started = time.perf_counter()
        grid, rays = fuse_views(views, estimate[station.key], estimate, self.params,
                                which="ceiling")  # fmt: skip
        made = _OwnMap(tuple(v.key for v in views), relative,
                       band_of_grid(grid, self.params, "ceiling"), rays=rays)  # fmt: skip
        return made, time.perf_counter() - started

    def _keep_own(self, station: Station, views: list[View], made: _OwnMap,
                  seconds: float) -> _OwnMap:  # fmt: skip
        self._own[station.key] = made
        work = self._work(station.key)
        work.own_rays += made.rays
        work.own_seconds += seconds
        work.own_builds += 1
        return made

    def prepare(
        self,
        stations: Iterable[Station],
        estimate: dict[int, np.ndarray],
        ties: dict[int, set[int]],
        workers: int = 1,
        clouds: bool = False,
    ) -> None:
        """Make the maps of ``stations`` not made yet (or whose views moved) and, with
        ``clouds`` (and registration configured), their registration clouds, up to ``workers``
        at a time, so that searches run side by side afterwards only read the maps. Fusion,
        the clouds' neighbour queries and their normals are compiled kernels that release the
        GIL; each map and cloud is the one :meth:`band` and :meth:`cloud` would make now."""
        stations = list(stations)
        stale: dict[int, tuple[Station, list[View], np.ndarray]] = {}
        for station in stations:
            wanted = self._own_wanted(station, estimate, ties)
            if wanted is not None and wanted[0] is None:
                stale[station.key] = (station, wanted[1], wanted[2])
        fused = side_by_side(lambda item: self._fuse_own(*item, estimate), list(stale.values()),
                             workers)  # fmt: skip
        for (station, views, _), (made, seconds) in zip(stale.values(), fused, strict=True):
            self._keep_own(station, views, made, seconds)
        registration = self.params.registration
        if not clouds or registration is None:
            return
        pending: dict[int, tuple[Station, list[View]]] = {}
        for station in stations:
            own = self._own_map(station, estimate, ties)
            if own is not None and own[0].cloud is None:
                pending[station.key] = (station, own[1])

        def make(item: tuple[Station, list[View]]) -> tuple[Cloud, float]:
            station, views = item
            started = time.perf_counter()
            cloud = cloud_of_views(views, estimate[station.key], estimate, self.params,
                                   registration)  # fmt: skip
            return cloud, time.perf_counter() - started

        clouds_made = side_by_side(make, list(pending.values()), workers)
        for (station, _), (cloud, seconds) in zip(pending.values(), clouds_made, strict=True):
            self._own[station.key].cloud = cloud
            self._work(station.key).own_seconds += seconds

    def band(
        self, station: Station, estimate: dict[int, np.ndarray], ties: dict[int, set[int]]
    ) -> Band | None:
        """The station's ceiling band in its own frame: kept while its views stay put."""
        own = self._own_map(station, estimate, ties)
        return None if own is None else own[0].band

    def cloud(
        self, station: Station, estimate: dict[int, np.ndarray], ties: dict[int, set[int]]
    ) -> Cloud | None:
        """The station's points (of the views its band is fused from) in its own frame, for
        registration; kept with its band. None without ``params.registration``."""
        registration = self.params.registration
        own = self._own_map(station, estimate, ties)
        if registration is None or own is None:
            return None
        kept, views = own
        if kept.cloud is None:
            started = time.perf_counter()
            kept.cloud = cloud_of_views(views, estimate[station.key], estimate, self.params,
                                        registration)  # fmt: skip
            self._work(station.key).own_seconds += time.perf_counter() - started
        return kept.cloud

    def older_cloud(
        self,
        anchor: Station,
        older: Sequence[Station],
        estimate: dict[int, np.ndarray],
        ties: dict[int, set[int]],
    ) -> Cloud | None:
        """The ``older`` stations' clouds in ``anchor``'s frame, joined."""
        frame = estimate[anchor.key]
        clouds = [
            cloud.moved(se2.between(frame, estimate[s.key]))
            for s in older
            if (cloud := self.cloud(s, estimate, ties)) is not None
        ]
        return Cloud.joined(clouds) if clouds else None

    def older_band(
        self,
        station: Station,
        anchor: Station,
        older: Sequence[Station],
        estimate: dict[int, np.ndarray],
        ties: dict[int, set[int]],
    ) -> Band | None:
        """The ceiling band of the ``older`` stations' views fused in ``anchor``'s frame (for
        ``station``'s loop closure): the anchor's grid so far, with the new views appended when
        those fused before are the first of the ones wanted and have not moved."""
        return self.older_bands([(station, anchor, older)], estimate, ties)[0]

    def older_bands(
        self,
        closures: Sequence[tuple[Station, Station, Sequence[Station]]],
        estimate: dict[int, np.ndarray],
        ties: dict[int, set[int]],
        workers: int = 1,
    ) -> list[Band | None]:
        """:meth:`older_band` of each (station, anchor, older stations), in order. The closures
        of one anchor are fused in their order, each appending to the grid the one before left;
        those of different anchors touch different grids and run side by side on up to
        ``workers`` threads. Every band is the one fusing its views at once gives, so the
        answers do not depend on the threads; a grid is never dropped while its anchor's
        closures run (only afterwards, the least recently used beyond ``_OLDER_GRIDS``)."""
        by_anchor: dict[int, list[int]] = {}
        for n, (_, anchor, _) in enumerate(closures):
            by_anchor.setdefault(anchor.key, []).append(n)
        # Each anchor's closures with the grid kept so far (taken out while they run). The grids
        # kept afterwards are the last used; the others are let go as soon as their anchor's
        # closures are done, so that at most one grid per thread is made at a time.
        groups: list[_OlderGroup] = [
            (key, numbers, self._older.pop(key, None)) for key, numbers in by_anchor.items()
        ]
        last_used = sorted(by_anchor, key=lambda k: by_anchor[k][-1])
        keep = set(last_used[-_OLDER_GRIDS:])

        def fuse(group: _OlderGroup) -> tuple[_OlderMap | None, list[_OlderMade]]:
            key, numbers, kept = group
            made: list[_OlderMade] = []
            for n in numbers:
                _, anchor, older = closures[n]
                kept, band, rays, seconds = self._older_step(kept, anchor, older, estimate, ties)
                made.append((band, rays, seconds))
            return (kept if key in keep else None), made

        fused = side_by_side(fuse, groups, workers)
        del groups  # the grids not kept go with their group's answer
        bands: list[Band | None] = [None] * len(closures)
        kept_by_anchor: dict[int, _OlderMap] = {}
        for (key, numbers), (kept, made) in zip(by_anchor.items(), fused, strict=True):
            for n, (band, rays, seconds) in zip(numbers, made, strict=True):
                bands[n] = band
                work = self._work(closures[n][0].key)
                work.older_rays += rays
                work.older_seconds += seconds
            if kept is not None:
                kept_by_anchor[key] = kept
        for key in last_used:
            if key in kept_by_anchor:
                self._older[key] = kept_by_anchor[key]
        while len(self._older) > _OLDER_GRIDS:
            self._older.popitem(last=False)
        return bands

    def _older_step(
        self,
        kept: _OlderMap | None,
        anchor: Station,
        older: Sequence[Station],
        estimate: dict[int, np.ndarray],
        ties: dict[int, set[int]],
    ) -> tuple[_OlderMap | None, Band | None, int, float]:
        """One closure's older-stations band from the anchor's grid ``kept`` (appended to, or
        rebuilt when its views are not the first of those wanted or moved): the grid now, the
        band, the rays cast and the seconds taken. Touches nothing shared but the views'
        reaches (any thread)."""
        views = [v for s in older for v in tied_views(s, ties) if v.key in estimate]
        if not views:
            return kept, None, 0, 0.0
        frame = estimate[anchor.key]
        relative = _relative(frame, views, estimate)
        keys = [v.key for v in views]
        started = time.perf_counter()
        fused = 0 if kept is None else len(kept.views)
        if (
            kept is None
            or keys[:fused] != kept.views
            or not self._still(kept.relative, relative[:fused], views[:fused])
        ):
            kept = _OlderMap([], np.zeros((0, 3)), OccupancyGrid(self.params.grid))
            fused = 0
        new = views[fused:]
        rays = 0
        if new:
            _, rays = fuse_views(new, frame, estimate, self.params, kept.grid, which="ceiling")
            kept.views = keys
            kept.relative = np.vstack([kept.relative, relative[fused:]])
        if kept.banded != len(kept.views):
            kept.band = band_of_grid(kept.grid, self.params, "ceiling")
            kept.banded = len(kept.views)
        return kept, kept.band, rays, time.perf_counter() - started

    def retain(self, keys: set[int]) -> None:
        """Forget the maps of every station not in ``keys`` (a long mission's worker keeps
        only the neighbourhood it searches in)."""
        self._own = {k: v for k, v in self._own.items() if k in keys}
        held = {k for m in self._own.values() for k in m.views}
        held |= {k for m in self._older.values() for k in m.views}
        self._reach = {i: kept for i, kept in self._reach.items() if kept[0].key in held}

    def searched(self, station: Station, seconds: float) -> None:
        """Count a search's wall time to the station searched."""
        self._work(station.key).search_seconds += seconds
