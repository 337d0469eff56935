"""What each search inside a mission found, as the report and the figures take it: the
:class:`SearchRecord` of every station link, loop closure and relocalization, and the
:class:`SearchPicture` a figure draws of one (docs/design.md §7, docs/results.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from estimation.search.exhaustive import SearchResult
from mapping.band import Band

__all__ = ["SearchPicture", "SearchRecord", "pose_of", "records_json"]


@dataclass(frozen=True, eq=False)
class SearchPicture:
    """What a figure of one search draws (the paper's Fig. 5b): the position PDF summed over the
    rotations, on the lattice searched, and the two bands matched, in the frame of the band
    searched against."""

    x_m: np.ndarray  # (X,)
    y_m: np.ndarray  # (Y,)
    marginal: np.ndarray  # (Y, X) float32, sums to 1
    against: Band  # the map searched
    local: Band  # the station's (or the sweep's) band, in its own frame

    @classmethod
    def of(cls, result: SearchResult, local: Band, against: Band) -> SearchPicture:
        marginal = result.prob.sum(axis=0, dtype=np.float64).astype(np.float32)
        return cls(result.x_m, result.y_m, marginal, against, local)


@dataclass(frozen=True)
class SearchRecord:
    """One search: what was matched against what, and the answer; loop closures and
    relocalizations keep their :class:`SearchPicture` for the result's figures."""

    station: str  # "a3"
    against: str  # the anchor station's label, or "map"
    kind: str  # "link" (predecessor), "loop" (older stations) or "relocalize"
    band: str  # "ceiling" or "floor"
    pose: tuple[float, float, float]  # in the anchor's (or the map's) frame
    peak_ratio: float
    dominant: bool
    used: bool  # became a factor
    seconds: float
    time_s: float  # when the station's sweeps were taken
    overlap: float = math.nan  # share of the local map's known cells on known map cells
    searched: tuple[float, float, float] | None = None  # the search's pose when refined
    inliers: float = math.nan  # the registration's share of corresponding points
    picture: SearchPicture | None = field(default=None, compare=False, repr=False)


def pose_of(result: SearchResult) -> tuple[float, float, float]:
    """The search's best pose as three floats (a record's ``pose``)."""
    x, y, yaw = (float(v) for v in result.pose)
    return x, y, yaw


def records_json(records: list[SearchRecord]) -> list[dict[str, Any]]:
    return [
        {
            **{k: v for k, v in r.__dict__.items() if k not in ("picture", "searched", "inliers")},
            "pose": [round(v, 6) for v in r.pose],
            "overlap": round(r.overlap, 4),
            **({} if r.searched is None else {"searched": [round(v, 6) for v in r.searched]}),
            **({} if math.isnan(r.inliers) else {"inliers": round(r.inliers, 4)}),
        }
        for r in records
    ]
