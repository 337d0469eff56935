"""Global localization inside a mission: station maps, ceiling bands, searches (DESIGN §5, §7).

Every reference station gets a local map — the sweeps of its dwells fused in the station's own
frame — and its ceiling band. Each station is then searched against the map of the *older*
stations near it (not its immediate predecessor, which already constrains it through the
mutual observations), expressed in the frame of the nearest of them: a dominant peak becomes a
``Localize`` event, a between-factor from that station (loop closure) whose covariance comes
from the PDF's peak. After the ``changes`` step, each robot's last sweep is localized against
the final map (ceiling band, and a floor band for comparison): those results are reported.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.config import Config
from estimation.errors import EstimationError
from estimation.events import Localize
from estimation.keys import pose_key
from estimation.search import SearchParams, windowed_search
from mapping.band import Band, extract_band
from mapping.errors import MapError
from mapping.fusion import Scan as MapScan
from mapping.fusion import fuse_scans
from mapping.grid import GridParams
from sensors.frames import pose2_matrix

if TYPE_CHECKING:
    from estimation.pipeline import Dataset, Sweep

__all__ = ["SearchRecord", "loop_closures", "relocalize", "search_params"]

#: Older stations farther than this from a station are not searched against it.
_NEIGHBOURHOOD_M = 12.0
#: A loop closure matches against stations at least this many stations older (a revisit):
#: recent neighbours are already tied by mutual observations, and corridors repeat along their
#: axis, so matching them adds false peaks rather than information.
_MIN_AGE = 4
#: A dominant peak becomes a factor only if it lies this close to the predicted pose.
_CONSISTENT_M = 2.0
_CONSISTENT_RAD = math.radians(30.0)


def search_params(config: Config) -> SearchParams:
    """The search's own configuration glue, so every ``search`` key (β, occupied level) applies."""
    from estimation.localize import search_params as from_section

    return from_section(config.search)


@dataclass(frozen=True)
class SearchRecord:
    """One search: what was matched against what, and the answer."""

    station: str  # "a3"
    against: str  # the anchor station's label, or "map"
    band: str  # "ceiling" or "floor"
    pose: tuple[float, float, float]  # in the anchor's (or the map's) frame
    peak_ratio: float
    dominant: bool
    used: bool  # became a factor
    seconds: float
    time_s: float  # when the station's sweeps were taken


def _scanner(pose: np.ndarray, config: Config) -> np.ndarray:
    return pose2_matrix(*pose) @ pose2_matrix(
        config.robot.scanner_x_m, 0.0, 0.0, config.robot.scanner_height_m
    )


def _band(sweeps: list[Sweep], frame: np.ndarray, estimate: dict[int, np.ndarray],
          config: Config, which: str) -> Band | None:  # fmt: skip
    """The band of the sweeps fused in the robot frame ``frame`` (a pose in the map frame)."""
    usable = [s for s in sweeps if pose_key(s.robot, s.index) in estimate]
    if not usable:
        return None
    T_frame_map = np.linalg.inv(pose2_matrix(*frame))
    transforms = np.stack(
        [T_frame_map @ _scanner(estimate[pose_key(s.robot, s.index)], config) for s in usable]
    )
    grid = fuse_scans(
        [MapScan(s.scan.points_scanner) for s in usable],
        transforms,
        GridParams(**config.grid.model_dump()),
    )
    limits = config.bands.ceiling if which == "ceiling" else config.bands.floor
    try:
        band = extract_band(grid, limits.min_m, limits.max_m)
    except MapError:
        return None
    return band if band.known.sum() > 50 else None


def _stations(dataset: Dataset, sweeps: list[Sweep]) -> list[tuple[str, int, float, list[Sweep]]]:
    """(robot, index, time, sweeps of its dwells) for every reference station, in time order."""
    by_dwell: dict[int, list[Sweep]] = {}
    for sweep in sweeps:
        by_dwell.setdefault(sweep.dwell, []).append(sweep)
    stations: dict[tuple[str, int], tuple[float, list[Sweep]]] = {}
    for number, event in enumerate(dataset.events):
        if (
            event["event"] != "dwell"
            or event.get("phase") == "relocalize"
            or not event.get("reference")
        ):
            continue
        reference = event["reference"]
        key = (reference, int(event["poses"][reference]))
        t, found = stations.get(key, (float(event["t_s"]), []))
        stations[key] = (t, found + by_dwell.get(number, []))
    return [(r, i, t, s) for (r, i), (t, s) in sorted(stations.items(), key=lambda kv: kv[1][0])]


def loop_closures(
    dataset: Dataset, sweeps: list[Sweep], estimate: dict[int, np.ndarray]
) -> tuple[list[Localize], list[SearchRecord]]:
    """Search each station against the older stations near it; dominant peaks become events."""
    config = dataset.config
    params = search_params(config)
    stations = _stations(dataset, sweeps)
    events: list[Localize] = []
    records: list[SearchRecord] = []
    for n, (robot, index, t, station_sweeps) in enumerate(stations):
        key = pose_key(robot, index)
        if key not in estimate or n < _MIN_AGE:
            continue
        here = estimate[key]
        older = [
            s for s in stations[: max(0, n - _MIN_AGE + 1)]
            if pose_key(s[0], s[1]) in estimate
            and math.dist(estimate[pose_key(s[0], s[1])][:2], here[:2]) < _NEIGHBOURHOOD_M
        ]  # fmt: skip
        if not older:
            continue
        anchor = min(older, key=lambda s: math.dist(estimate[pose_key(s[0], s[1])][:2], here[:2]))
        anchor_pose = estimate[pose_key(anchor[0], anchor[1])]
        local = _band(station_sweeps, here, estimate, config, "ceiling")
        global_ = _band(
            [s for st in older for s in st[3]], anchor_pose, estimate, config, "ceiling"
        )
        if local is None or global_ is None:
            continue
        predicted = np.linalg.inv(pose2_matrix(*anchor_pose)) @ pose2_matrix(*here)
        started = time.perf_counter()
        try:
            found = windowed_search(
                local, global_, params, predicted[:2, 3], config.search.window_m,
                2 * config.search.window_m,
            )  # fmt: skip
        except EstimationError:
            continue
        result = found.result
        predicted_yaw = math.atan2(predicted[1, 0], predicted[0, 0])
        consistent = (
            math.dist(result.pose[:2], predicted[:2, 3]) < _CONSISTENT_M
            and abs(math.remainder(result.pose[2] - predicted_yaw, 2 * math.pi)) < _CONSISTENT_RAD
        )
        use = found.dominant and consistent
        if use:
            events.append(Localize(robot, index, result.pdf, reference=(anchor[0], anchor[1])))
        records.append(
            SearchRecord(
                station=f"{robot}{index}", against=f"{anchor[0]}{anchor[1]}", band="ceiling",
                pose=tuple(float(v) for v in result.pose),  # type: ignore[arg-type]
                peak_ratio=float(result.peak_ratio), dominant=found.dominant, used=use,
                seconds=time.perf_counter() - started, time_s=t,
            )
        )  # fmt: skip
    return events, records


def relocalize(
    dataset: Dataset, sweeps: list[Sweep], estimate: dict[int, np.ndarray]
) -> list[SearchRecord]:
    """After the changes: each robot's sweep against the mission's map, ceiling and floor band."""
    config = dataset.config
    params = search_params(config)
    numbers = [n for n, e in enumerate(dataset.events)
               if e["event"] == "dwell" and e.get("phase") == "relocalize"]  # fmt: skip
    mapped = [s for s in sweeps if s.dwell not in numbers]
    records: list[SearchRecord] = []
    origin = np.zeros(3)
    for number in numbers:
        event = dataset.events[number]
        for sweep in (s for s in sweeps if s.dwell == number):
            key = pose_key(sweep.robot, sweep.index)
            if key not in estimate:
                continue
            dwell_sweeps = [s for s in sweeps if s.dwell == number]
            for which in ("ceiling", "floor"):
                # The local map around the robot: every sweep of the dwell, in its frame.
                local = _band(dwell_sweeps, estimate[key], estimate, config, which)
                global_ = _band(mapped, origin, estimate, config, which)
                if local is None or global_ is None:
                    continue
                started = time.perf_counter()
                try:
                    found = windowed_search(
                        local, global_, params, estimate[key][:2], config.search.window_m,
                        config.search.max_window_m,
                    )  # fmt: skip
                except EstimationError:
                    continue
                records.append(
                    SearchRecord(
                        station=f"{sweep.robot}{sweep.index}", against="map", band=which,
                        pose=tuple(float(v) for v in found.result.pose),  # type: ignore[arg-type]
                        peak_ratio=float(found.result.peak_ratio), dominant=found.dominant,
                        used=False, seconds=time.perf_counter() - started,
                        time_s=float(event["t_s"]),
                    )
                )  # fmt: skip
    return records


def records_json(records: list[SearchRecord]) -> list[dict[str, Any]]:
    return [{**r.__dict__, "pose": [round(v, 6) for v in r.pose]} for r in records]
