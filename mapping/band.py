"""2D grids cut from a 3D map: the paper's sub-ceiling cross-section, or any height band.

The vertical columns of the band are summed and re-normalised (docs/design.md §6): a cell of the 2D
grid holds the share of the band's voxel layers that are occupied in its column — the same
quantity ``sensors.sim.truth.band_share`` computes from a world's ground truth, so the two can
be compared cell for cell. A column is *known* when at least one of its band cells has been
observed; unknown columns hold 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapping.errors import MapError
from mapping.grid import OccupancyGrid
from mapping.logodds import logodds

__all__ = ["Band", "band_layers", "extract_band"]

#: Cell centres this close (in cells) to a band edge count as on it (float round-off).
_EDGE_EPS = 1e-6


@dataclass(frozen=True)
class Band:
    """A 2D grid over (x, y): row = y, column = x, cell (0, 0) at ``lower_xy``."""

    occupancy: np.ndarray  # (H, W) in [0, 1]: share of the band's layers occupied
    known: np.ndarray  # (H, W) bool: some band cell of the column was observed
    lower_xy: np.ndarray  # (2,) corner of cell (row 0, col 0), in the map's frame
    resolution_m: float

    def __post_init__(self) -> None:
        occupancy = np.asarray(self.occupancy, dtype=np.float64)
        known = np.asarray(self.known, dtype=bool)
        if occupancy.ndim != 2 or known.shape != occupancy.shape:
            raise MapError(
                f"band occupancy and known mask must be equal 2D shapes, got {occupancy.shape} "
                f"and {known.shape}"
            )
        if not (math.isfinite(self.resolution_m) and self.resolution_m > 0):
            raise MapError(f"band resolution must be positive, got {self.resolution_m!r}")
        object.__setattr__(self, "occupancy", occupancy)
        object.__setattr__(self, "known", known)
        object.__setattr__(self, "lower_xy", np.asarray(self.lower_xy, dtype=np.float64))

    @property
    def shape(self) -> tuple[int, int]:
        rows, cols = self.occupancy.shape
        return rows, cols

    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the grid, for plotting."""
        rows, cols = self.shape
        x0, y0 = float(self.lower_xy[0]), float(self.lower_xy[1])
        return (x0, x0 + cols * self.resolution_m, y0, y0 + rows * self.resolution_m)

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) x and y of the cell centres."""
        rows, cols = self.shape
        xs = self.lower_xy[0] + (np.arange(cols) + 0.5) * self.resolution_m
        ys = self.lower_xy[1] + (np.arange(rows) + 0.5) * self.resolution_m
        gx, gy = np.meshgrid(xs, ys)
        return gx, gy


def band_layers(
    origin_z_m: float, resolution_m: float, z_min_m: float, z_max_m: float
) -> tuple[int, int]:
    """First and last layer k whose cell centres lie at heights within [z_min_m, z_max_m)."""
    if not z_min_m < z_max_m:
        raise MapError(f"a band must run upwards, got [{z_min_m}, {z_max_m}]")
    first = math.ceil((z_min_m - origin_z_m) / resolution_m - 0.5 - _EDGE_EPS)
    last = math.ceil((z_max_m - origin_z_m) / resolution_m - 0.5 - _EDGE_EPS) - 1
    if last < first:
        raise MapError(
            f"the band [{z_min_m}, {z_max_m}) m holds no cell centre at {resolution_m} m cells"
        )
    return first, last


def extract_band(
    grid: OccupancyGrid,
    z_min_m: float,
    z_max_m: float,
    *,
    threshold: float | None = None,
    free_min_observed: float = 0.0,
    lower_xy: np.ndarray | tuple[float, float] | None = None,
    upper_xy: np.ndarray | tuple[float, float] | None = None,
) -> Band:
    """Sum the grid's columns over a height band and re-normalise (docs/design.md §6).

    A band cell's value is the number of occupied cells (P > ``threshold``, default the grid's)
    among the band's layers in its column, divided by the number of layers. A column is known
    when it holds an occupied layer, or when at least ``free_min_observed`` (a share) of its
    layers were observed: a column seen free only through a layer or two — rays passing just under
    a beam, whose other layers nobody saw — is then unknown rather than free, so that two maps
    of the same place seen from different viewpoints agree. The 2D grid covers
    the columns overlapping the rectangle [lower_xy, upper_xy], by default the bounding box of
    the band's known cells; MapError if the band has no known cell and no rectangle is given.
    """
    if not 0.0 <= free_min_observed <= 1.0:
        raise MapError(f"free_min_observed must lie in [0, 1], got {free_min_observed!r}")
    res = grid.resolution_m
    origin = grid.origin_m
    first, last = band_layers(float(origin[2]), res, z_min_m, z_max_m)
    layers = last - first + 1
    cells, values = grid.cells(z_range=(first, last))
    if lower_xy is None or upper_xy is None:
        if len(cells) == 0:
            raise MapError(f"the band [{z_min_m}, {z_max_m}) m holds no observed cell")
        lo_ij = cells[:, :2].min(axis=0)
        hi_ij = cells[:, :2].max(axis=0)
    else:
        lo_ij = np.floor((np.asarray(lower_xy, float) - origin[:2]) / res).astype(np.int64)
        hi_ij = np.floor((np.asarray(upper_xy, float) - origin[:2]) / res).astype(np.int64)
        if np.any(hi_ij < lo_ij):
            raise MapError(f"empty rectangle: lower {lower_xy}, upper {upper_xy}")
    cols, rows = (hi_ij - lo_ij + 1).tolist()
    counts = np.zeros((rows, cols), dtype=np.int64)
    ij = cells[:, :2] - lo_ij
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < cols) & (ij[:, 1] >= 0) & (ij[:, 1] < rows)
    ij, values = ij[inside], values[inside]
    level = grid.params.logodds_threshold if threshold is None else float(logodds(threshold))
    occupied = values > level
    np.add.at(counts, (ij[occupied, 1], ij[occupied, 0]), 1)
    observed = np.zeros((rows, cols), dtype=np.int64)
    np.add.at(observed, (ij[:, 1], ij[:, 0]), 1)
    known = (counts > 0) | ((observed > 0) & (observed >= free_min_observed * layers))
    return Band(
        occupancy=counts / layers,
        known=known,
        lower_xy=origin[:2] + lo_ij * res,
        resolution_m=res,
    )
