"""The occupancy grid's parameters: its lattice (resolution, origin, block size) and its sensor
model (hit and miss probabilities, clamping, the occupied threshold, no-return beams), checked
when made (``mapping.grid`` re-exports them)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from mapping.errors import MapError
from mapping.logodds import logodds

__all__ = ["MIN_RESOLUTION_M", "GridParams", "open_probability"]

#: The finest cell a grid may have: finer cells multiply memory by the cube of the ratio (a
#: 0.5 mm grid of one room needs gigabytes) and are far below the LMS 200's range noise.
MIN_RESOLUTION_M = 0.005


def _finite_positive(name: str, value: float) -> None:
    if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
        raise MapError(f"{name} must be a positive number, got {value!r}")


def open_probability(name: str, value: float) -> None:
    """Refuse a probability ``name`` outside (0, 1)."""
    if not (isinstance(value, int | float) and 0.0 < value < 1.0):
        raise MapError(f"{name} must lie in (0, 1), got {value!r}")


@dataclass(frozen=True)
class GridParams:
    """Lattice and sensor model of a grid. Field names and defaults are those of the ``grid``
    section of the configuration (OctoMap's defaults), so ``GridParams(**config.grid.model_dump())``
    builds one; ``origin_m`` (the corner of cell (0, 0, 0), map frame) is 0 there.
    """

    resolution_m: float = 0.1
    prob_hit: float = 0.7
    prob_miss: float = 0.4
    clamp_min: float = 0.1192
    clamp_max: float = 0.971
    occupied_threshold: float = 0.5
    no_return_free_m: float = 4.0
    block_size_cells: int = 16
    origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        _finite_positive("resolution_m", self.resolution_m)
        if self.resolution_m < MIN_RESOLUTION_M:
            raise MapError(
                f"resolution_m must be at least {MIN_RESOLUTION_M} m, got {self.resolution_m!r}"
            )
        for name in ("prob_hit", "prob_miss", "clamp_min", "clamp_max", "occupied_threshold"):
            open_probability(name, getattr(self, name))
        if not self.prob_miss < 0.5 < self.prob_hit:
            raise MapError(
                f"need prob_miss < 0.5 < prob_hit, got {self.prob_miss} and {self.prob_hit}"
            )
        if not self.clamp_min < self.occupied_threshold < self.clamp_max:
            raise MapError(
                "need clamp_min < occupied_threshold < clamp_max, got "
                f"{self.clamp_min}, {self.occupied_threshold}, {self.clamp_max}"
            )
        if not (math.isfinite(self.no_return_free_m) and self.no_return_free_m >= 0):
            raise MapError(f"no_return_free_m must be ≥ 0, got {self.no_return_free_m!r}")
        if not (isinstance(self.block_size_cells, int) and 2 <= self.block_size_cells <= 256):
            raise MapError(
                f"block_size_cells must be an integer in [2, 256], got {self.block_size_cells!r}"
            )
        origin = tuple(float(v) for v in self.origin_m)
        if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
            raise MapError(f"origin_m must be three finite numbers, got {self.origin_m!r}")
        object.__setattr__(self, "origin_m", origin)

    @property
    def logodds_hit(self) -> float:
        return float(logodds(self.prob_hit))

    @property
    def logodds_miss(self) -> float:
        return float(logodds(self.prob_miss))

    @property
    def logodds_min(self) -> float:
        return float(logodds(self.clamp_min))

    @property
    def logodds_max(self) -> float:
        return float(logodds(self.clamp_max))

    @property
    def logodds_threshold(self) -> float:
        return float(logodds(self.occupied_threshold))

    def same_lattice(self, other: GridParams) -> bool:
        """Whether two grids share resolution, origin and block size (and can be merged)."""
        return (
            self.resolution_m == other.resolution_m
            and self.origin_m == other.origin_m
            and self.block_size_cells == other.block_size_cells
        )
