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

__all__ = [
    "Band",
    "CeilingRule",
    "band_layers",
    "band_slab_m",
    "extract_band",
    "extract_ceiling_band",
]

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

    def known_centers(self) -> np.ndarray:
        """(n, 2) x, y of the known cells' centres."""
        gx, gy = self.cell_centers()
        return np.column_stack([gx[self.known], gy[self.known]])

    def covers(self, xy: np.ndarray) -> np.ndarray:
        """(n,) bool: which of the (n, 2) points fall on a known cell (outside the grid: no)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        ij = np.floor((xy - self.lower_xy) / self.resolution_m)
        ij[~np.isfinite(ij)] = -1.0
        rows, cols = self.shape
        inside = (ij >= 0).all(axis=1) & (ij[:, 0] < cols) & (ij[:, 1] < rows)
        covered = np.zeros(len(xy), dtype=bool)
        i, j = ij[inside].astype(np.int64).T
        covered[inside] = self.known[j, i]
        return covered


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


def band_slab_m(
    origin_z_m: float, resolution_m: float, z_min_m: float, z_max_m: float
) -> tuple[float, float]:
    """The heights (low, high) a ray must reach into to change a cell of the band's layers
    (:func:`band_layers`), with one cell to spare on either side: fusing only such rays
    (:func:`mapping.fusion.fuse_scans`' ``z_slab``) gives the band's cells exactly as fusing
    every ray does."""
    first, last = band_layers(origin_z_m, resolution_m, z_min_m, z_max_m)
    return origin_z_m + (first - 1) * resolution_m, origin_z_m + (last + 2) * resolution_m


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
    ij = cells[:, :2] - lo_ij
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < cols) & (ij[:, 1] >= 0) & (ij[:, 1] < rows)
    ij, values = ij[inside], values[inside]
    level = grid.params.logodds_threshold if threshold is None else float(logodds(threshold))
    occupied = values > level
    counts = _per_cell(ij[occupied, 1], ij[occupied, 0], (rows, cols))
    observed = _per_cell(ij[:, 1], ij[:, 0], (rows, cols))
    known = (counts > 0) | ((observed > 0) & (observed >= free_min_observed * layers))
    return Band(
        occupancy=counts / layers,
        known=known,
        lower_xy=origin[:2] + lo_ij * res,
        resolution_m=res,
    )


def _per_cell(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) int64: how many of the (row, col) pairs fall on each cell (``np.add.at``'s
    counts, by ``np.bincount``: several times faster)."""
    flat = np.bincount(rows * shape[1] + cols, minlength=shape[0] * shape[1])
    return flat.reshape(shape).astype(np.int64, copy=False)


@dataclass(frozen=True)
class CeilingRule:
    """A band that follows the ceiling it sees: under each column, ``depth_m`` of layers ending
    ``gap_m`` below the ceiling of its neighbourhood (the highest occupied layer of the columns
    within ``smooth_m``, their median). ``fallback_m`` is the fixed band used when no ceiling
    was seen at all."""

    depth_m: float = 0.6
    gap_m: float = 0.1
    smooth_m: float = 1.0
    fallback_m: tuple[float, float] = (2.3, 2.9)
    #: True: the fixed band ``fallback_m``, cut off ``gap_m`` below the ceiling where the
    #: ceiling is lower than its top (and kept two layers deep), instead of following it.
    clip: bool = False

    def __post_init__(self) -> None:
        for name in ("depth_m", "gap_m", "smooth_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise MapError(f"ceiling band: {name} must be a finite length >= 0, got {value!r}")
        if self.depth_m <= 0:
            raise MapError(f"ceiling band: depth_m must be positive, got {self.depth_m!r}")


def _column_layers(
    cells: np.ndarray, occupied: np.ndarray, lo_ij: np.ndarray, shape: tuple[int, int],
    rule: CeilingRule, res: float, origin_z: float,
) -> tuple[np.ndarray, np.ndarray] | None:  # fmt: skip
    """Per column of the rectangle (rows, cols): the first and last layer of its band, or None
    when no column shows a ceiling."""
    from scipy import ndimage

    rows, cols = shape
    ij = cells[:, :2] - lo_ij
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < cols) & (ij[:, 1] >= 0) & (ij[:, 1] < rows)
    top = np.full((rows, cols), np.iinfo(np.int64).min, dtype=np.int64)
    hit = inside & occupied
    np.maximum.at(top, (ij[hit, 1], ij[hit, 0]), cells[hit, 2])
    seen = top > np.iinfo(np.int64).min
    if not seen.any():
        return None
    # Every column takes the ceiling of the nearest column that saw one, then the median of its
    # neighbourhood: a luminaire that hid the ceiling above it, or a cupboard whose top was the
    # highest return, does not move the band; the ceiling of a room does.
    _, nearest = ndimage.distance_transform_edt(~seen, return_indices=True)
    filled = top[nearest[0], nearest[1]]
    size = 2 * max(0, round(rule.smooth_m / res / 2)) + 1
    ceiling = ndimage.median_filter(filled, size=size, mode="nearest") if size > 1 else filled
    last = ceiling - max(1, round(rule.gap_m / res))
    if rule.clip:
        fixed_first, fixed_last = band_layers(origin_z, res, *rule.fallback_m)
        last = np.minimum(last, fixed_last)
        return np.minimum(fixed_first, last - 1), last
    first = last - max(1, round(rule.depth_m / res)) + 1
    return first, last


def extract_ceiling_band(
    grid: OccupancyGrid,
    rule: CeilingRule,
    *,
    threshold: float | None = None,
    free_min_observed: float = 0.0,
    lower_xy: np.ndarray | tuple[float, float] | None = None,
    upper_xy: np.ndarray | tuple[float, float] | None = None,
) -> Band:
    """A band under every ceiling (see :class:`CeilingRule`): as :func:`extract_band`, but each
    column sums its own layers, so high halls and low offices are each cut just below their
    own ceiling structure. Falls back to the rule's fixed band when no ceiling was seen."""
    if not 0.0 <= free_min_observed <= 1.0:
        raise MapError(f"free_min_observed must lie in [0, 1], got {free_min_observed!r}")
    res = grid.resolution_m
    origin = grid.origin_m
    cells, values = grid.cells()
    if len(cells) == 0:
        raise MapError("the ceiling band holds no observed cell: the grid is empty")
    if lower_xy is None or upper_xy is None:
        lo_ij, hi_ij = cells[:, :2].min(axis=0), cells[:, :2].max(axis=0)
    else:
        lo_ij = np.floor((np.asarray(lower_xy, float) - origin[:2]) / res).astype(np.int64)
        hi_ij = np.floor((np.asarray(upper_xy, float) - origin[:2]) / res).astype(np.int64)
        if np.any(hi_ij < lo_ij):
            raise MapError(f"empty rectangle: lower {lower_xy}, upper {upper_xy}")
    level = grid.params.logodds_threshold if threshold is None else float(logodds(threshold))
    occupied = values > level
    cols, rows = (hi_ij - lo_ij + 1).tolist()
    layers = _column_layers(cells, occupied, lo_ij, (rows, cols), rule, res, float(origin[2]))
    if layers is None:
        return extract_band(grid, *rule.fallback_m, threshold=threshold,
                            free_min_observed=free_min_observed, lower_xy=lower_xy,
                            upper_xy=upper_xy)  # fmt: skip
    first, last = layers
    ij = cells[:, :2] - lo_ij
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < cols) & (ij[:, 1] >= 0) & (ij[:, 1] < rows)
    r, c, k = ij[inside, 1], ij[inside, 0], cells[inside, 2]
    in_band = (k >= first[r, c]) & (k <= last[r, c])
    r, c, occ = r[in_band], c[in_band], occupied[inside][in_band]
    counts = _per_cell(r[occ], c[occ], (rows, cols))
    observed = _per_cell(r, c, (rows, cols))
    depth = (last - first + 1).astype(np.float64)
    known = (counts > 0) | ((observed > 0) & (observed >= free_min_observed * depth))
    band = Band(counts / depth, known, origin[:2] + lo_ij * res, res)
    if lower_xy is not None and upper_xy is not None:
        return band
    if not known.any():
        raise MapError("the ceiling band holds no observed cell")
    rr, cc = np.nonzero(known)
    r0, r1, c0, c1 = rr.min(), rr.max() + 1, cc.min(), cc.max() + 1
    return Band(band.occupancy[r0:r1, c0:c1], known[r0:r1, c0:c1],
                band.lower_xy + np.array([c0, r0]) * res, res)  # fmt: skip
