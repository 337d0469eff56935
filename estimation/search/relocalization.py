"""Relocalization after the changes: each robot's sweep against the mission's map, ceiling and
floor band, refined on the mapped points (docs/design.md §5, §7). Reported, not used."""

from __future__ import annotations

import functools
import time
from typing import Any

import numpy as np

from estimation.errors import EstimationError
from estimation.search.exhaustive import overlap_fraction, windowed_search
from estimation.search.records import SearchPicture, SearchRecord, pose_of
from estimation.search.registration import Cloud, Registration, register
from estimation.search.station_maps import (
    Dwell,
    StationParams,
    View,
    cloud_of_views,
    fuse_band,
)
from mapping.band import Band

__all__ = ["relocalize"]


def relocalize(
    dwells: list[Dwell],
    mapped: list[View],
    estimate: dict[int, np.ndarray],
    params: StationParams,
) -> list[SearchRecord]:
    """After the changes: each robot's sweep of each dwell (its local map: every view of the
    dwell, in its frame) against the map of the ``mapped`` views, ceiling and floor band. With
    ``params.registration`` the sweep's points are then registered on the mapped points at the
    modes of both bands' PDFs, and the registration that lays the most points on the map is
    each record's pose (the band's search pose kept beside it): a band whose best mode is wrong
    (a high hall's ceiling band after the clutter moved) still gets the robot's pose when the
    other band or a lesser mode holds it."""
    records: list[SearchRecord] = []
    origin = np.zeros(3)
    whole: dict[str, Band | None] = {}  # the map of the mapped views, fused once per band
    points = _MapPoints(mapped, estimate, params)
    search = params.search
    for dwell in dwells:
        for view in dwell.views:
            if view.key not in estimate:
                continue
            started = time.perf_counter()
            searched = []
            for which in ("ceiling", "floor"):
                local = fuse_band(list(dwell.views), estimate[view.key], estimate, params, which)
                if which not in whole:
                    whole[which] = fuse_band(mapped, origin, estimate, params, which)
                global_ = whole[which]
                if local is None or global_ is None:
                    continue
                try:
                    found = windowed_search(
                        local, global_, search, estimate[view.key][:2], params.window_m,
                        params.max_window_m,
                    )  # fmt: skip
                except EstimationError:
                    continue
                searched.append((which, found, local, global_))
            candidates = [
                mode
                for _, found, _, _ in searched
                for mode in found.result.modes(
                    _RELOCALIZE_MODES, search.peak_radius_m, search.peak_radius_rad
                )
            ]
            sweep = points.of_dwell(dwell, estimate[view.key], estimate) if candidates else None
            verified = points.verified(sweep, candidates)
            seconds = time.perf_counter() - started
            for which, found, local, global_ in searched:
                fields: dict[str, Any] = {"pose": pose_of(found.result)}
                if verified is not None:
                    x, y, yaw = (float(v) for v in verified.pose)
                    fields = {"pose": (x, y, yaw), "searched": pose_of(found.result),
                              "inliers": verified.inliers}  # fmt: skip
                records.append(
                    SearchRecord(
                        station=f"{view.robot}{view.index}", against="map", band=which,
                        kind="relocalize", **fields,
                        peak_ratio=float(found.result.peak_ratio), dominant=found.dominant,
                        used=False, seconds=seconds, time_s=dwell.time_s,
                        overlap=overlap_fraction(local, global_, found.result.pose),
                        picture=SearchPicture.of(found.result, local, global_),
                    )
                )  # fmt: skip
    return records


#: Relocalization registers the sweep at this many modes of each band's search PDF.
_RELOCALIZE_MODES = 5


class _MapPoints:
    """The mapped views' points as a registration cloud in the map frame (made when first
    needed), against which relocalizations are verified and refined (``params.registration``;
    without it, nothing is)."""

    def __init__(
        self, mapped: list[View], estimate: dict[int, np.ndarray], params: StationParams
    ) -> None:
        self.mapped, self.estimate, self.params = mapped, estimate, params

    @functools.cached_property
    def cloud(self) -> Cloud | None:
        registration = self.params.registration
        if registration is None or not self.mapped:
            return None
        views = [v for v in self.mapped if v.key in self.estimate]
        return cloud_of_views(views, np.zeros(3), self.estimate, self.params, registration)

    def of_dwell(
        self, dwell: Dwell, frame: np.ndarray, estimate: dict[int, np.ndarray]
    ) -> Cloud | None:
        registration = self.params.registration
        if registration is None:
            return None
        views = [v for v in dwell.views if v.key in estimate]  # a robot never tied: no pose
        return cloud_of_views(views, frame, estimate, self.params, registration)

    def verified(self, sweep: Cloud | None, candidates: list[np.ndarray]) -> Registration | None:
        """The registration of ``sweep`` that lays the most of its points on the map, over the
        candidate poses (the search PDF's modes); None when none is accepted."""
        settings = self.params.registration
        if settings is None or sweep is None or self.cloud is None:
            return None
        best: Registration | None = None
        reach = sweep.reach_m() + settings.max_distance_m
        for seed in candidates:
            found = register(sweep, self.cloud.within(seed[:2], reach), seed, settings)
            if found is None or not found.accepted(settings):
                continue
            if best is None or found.inlier_points > best.inlier_points:
                best = found
        return best
