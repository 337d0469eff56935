"""The pose lattice and the metric, shared by the exhaustive search and the branch and bound.

**Metric.** Each known cell of a band with occupancy p (the share of the band's layers that
are occupied in its column) gets the value

    v(p) = min(1, (p − τ)/τ)    for p ≥ τ   (occupied evidence, +1 from 2τ up)
    v(p) = w · (p − τ)/τ        for p < τ   (free evidence, down to −w at p = 0)

with τ = ``occupied_level`` (default 0.1: a column with any occupied layer out of the ceiling
band's six is occupied evidence) and w = ``free_weight``; unknown cells get 0. The score of a
pose T (of the local grid's frame in the global grid's frame) is the correlation

    score(T) = Σ_k v_L(k) · v_G(cell of the global grid containing T·c_k)

over the known local cells k with centres c_k: occupied on occupied and free on free agree
(positive), occupied on free disagree (negative), and an unknown cell on either side — or a
local cell that falls off the global grid — counts nothing (docs/design.md §7, paper §2.2; the PDF
it gives: ``peak``).

**Scores.** ``agreement`` is the correlation above. Every known cell on a known cell adds the
product of the two values whether or not the pose is right, so a pose where more of the view's
free cells lie on free map cells gains from the overlap alone: free on free adds w² per cell.
``centred`` correlates the values less their band's mean over its known cells, m_L and m_G:

    score(T) = Σ_k (v_L(k) − m_L) · (v_G(T·c_k) − m_G)     (unknown cells still count 0)

          = agreement − m_G·Σ v_L − m_L·Σ v_G + m_L·m_G·N,

the sums over the N local cells that land on known map cells. If the local values were
unrelated to the map's under the pose (a wrong pose), each of the N products would average
mean(v_L·v_G) − m_L·m_G = 0: a wrong pose's expected score is 0 whatever its overlap, and only
agreement beyond the bands' proportions of occupied and free cells counts. It is still one
correlation (of the centred images), so the FFT search, the per-pose loop, the branch and bound
and the refinement compute it exactly; the means are those of the whole bands (a search over a
crop of the map passes the whole map's mean).

``excess`` keeps the agreement's values and subtracts what the overlap alone gives:

    score(T) = agreement(T) − m_L·m_G·N(T),

N(T) the number of local known cells on known map cells (a second correlation, of the known
masks). Under a wrong pose each overlapping cell's product averages m_L·m_G, so its expected
score is 0 as well, but unlike ``centred`` the weights of the cell pairs stay the agreement's,
less one constant: free on free still counts (0.25 − m_L·m_G), occupied on free costs more.
The branch and bound does not bound it: ``exhaustive.best_pose`` searches exhaustively for it.

**Lattice.** Translations step by the grids' resolution r; their lattice is offset so that at
θ = 0 local cell centres land on global cell centres; rotations step by 2π/T over the whole
circle. The global cell "containing" a point is ⌊(q − origin)/r⌋ per axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimation.errors import EstimationError
from mapping.band import Band

__all__ = [
    "EDGE",
    "MASK_METRIC",
    "QUARTER",
    "SCORES",
    "TIE",
    "Cells",
    "Metric",
    "check_pair",
    "covers_circle",
    "frac",
    "known_mask",
    "lattice_steps",
    "local_cells",
    "match_values",
    "overlap_weight",
    "pose_lattice",
    "quarter_lattice",
    "rotation_matrices",
    "value_mean",
    "yaw_lattice",
]

#: Fractions of a cell this close to an integer count as on it (float round-off in origins).
_SNAP = 1e-6
#: A point within this many cells below a cell boundary belongs to the cell above it, so that
#: centres exactly on a boundary (e.g. on the diagonal at 45°) fall the same way whatever the
#: float round-off.
EDGE = 1e-9
#: Rotated centres this close to a boundary are ties: the quarter-turn shortcut is not used.
TIE = 1e-7
#: The quarter-turn rotation on integer (x, y) vectors: R·(x, y) = (−y, x).
QUARTER = np.array([[0, -1], [1, 0]], dtype=np.int64)


#: The scores a search can correlate (see the module).
SCORES = ("agreement", "centred", "excess")


@dataclass(frozen=True)
class Metric:
    """How band occupancy becomes the cell values the score correlates (see the module)."""

    free_weight: float = 0.5
    occupied_level: float = 0.1
    score: str = "agreement"

    def __post_init__(self) -> None:
        if self.score not in SCORES:
            raise EstimationError(
                f"search score must be one of {', '.join(SCORES)}, got {self.score!r}"
            )
        if not (math.isfinite(self.free_weight) and self.free_weight >= 0):
            raise EstimationError(f"search free_weight must be >= 0, got {self.free_weight!r}")
        if not 0 < self.occupied_level < 1:
            raise EstimationError(
                f"search occupied_level must lie in (0, 1), got {self.occupied_level!r}"
            )


#: A metric under which occupancy 1 is value 1: ``known_mask`` bands give their known masks.
MASK_METRIC = Metric(free_weight=0.5, occupied_level=0.5)


def match_values(band: Band, metric: Metric, mean: float | None = None) -> np.ndarray:
    """(H, W) float64 cell values of the metric: occupied evidence up to +1, free evidence down
    to −``free_weight``, 0 on unknown cells; with the ``centred`` score, known cells less
    ``mean`` (default: the band's own, ``value_mean``). EstimationError on occupancy outside
    [0, 1] or NaN on a known cell."""
    values = _agreement_values(band, metric)
    if metric.score != "centred":
        return values  # ``excess`` correlates the agreement's values, then subtracts its term
    known = np.asarray(band.known, dtype=bool)
    centre = _known_mean(values, known) if mean is None else float(mean)
    return np.asarray(np.where(known, values - centre, 0.0))


def overlap_weight(local: Band, global_: Band, metric: Metric, global_mean: float | None) -> float:
    """The ``excess`` score's weight c of the overlap count (m_L·m_G, ``global_mean`` standing
    for the global band's mean when given); 0 for the other scores."""
    if metric.score != "excess":
        return 0.0
    m_g = value_mean(global_, metric) if global_mean is None else float(global_mean)
    return value_mean(local, metric) * m_g


def known_mask(band: Band) -> Band:
    """The band with occupancy 1 on its known cells: under ``MASK_METRIC`` its values are its
    known mask, and their correlation counts the overlapping cells."""
    known = np.asarray(band.known, dtype=bool)
    return Band(np.where(known, 1.0, 0.0), known, band.lower_xy, band.resolution_m)


def value_mean(band: Band, metric: Metric) -> float:
    """The mean ``agreement`` value over the band's known cells, the centre of the ``centred``
    score; 0 on a band with no known cell."""
    return _known_mean(_agreement_values(band, metric), np.asarray(band.known, dtype=bool))


def _known_mean(values: np.ndarray, known: np.ndarray) -> float:
    count = int(np.count_nonzero(known))
    return float(values[known].sum()) / count if count else 0.0


def _agreement_values(band: Band, metric: Metric) -> np.ndarray:
    occupancy = np.asarray(band.occupancy, dtype=np.float64)
    known = np.asarray(band.known, dtype=bool)
    if known.any():
        p = occupancy[known]
        if not np.isfinite(p).all() or p.min() < 0.0 or p.max() > 1.0:
            raise EstimationError("band occupancy must lie within [0, 1] on known cells")
    level = metric.occupied_level
    excess = (np.where(known, occupancy, level) - level) / level
    v = np.where(excess < 0.0, metric.free_weight * excess, np.minimum(excess, 1.0))
    return np.asarray(v)


def yaw_lattice(angular_resolution_rad: float) -> np.ndarray:
    """(T,) yaws 0, Δ, …, 2π − Δ; EstimationError unless Δ divides the circle."""
    count = round(2.0 * math.pi / angular_resolution_rad)
    if count < 1 or abs(count * angular_resolution_rad - 2.0 * math.pi) > 1e-6:
        raise EstimationError(
            f"angular resolution {math.degrees(angular_resolution_rad):g}° must divide 360°"
        )
    return np.arange(count) * (2.0 * math.pi / count)


def quarter_lattice(yaw_rad: np.ndarray) -> bool:
    """Whether ``yaw_rad`` is a whole-circle lattice (``yaw_lattice``) whose quarter turns are
    lattice rotations: the quarter-turn shortcut needs both."""
    count = len(yaw_rad)
    return count % 4 == 0 and bool(
        np.allclose(yaw_rad, np.arange(count) * (2.0 * math.pi / count), rtol=0.0, atol=1e-9)
    )


def rotation_matrices(yaw_rad: np.ndarray) -> np.ndarray:
    """(T, 2, 2) rotation matrices, exact at multiples of 90°."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    for arr in (c, s):
        arr[np.abs(arr) < 1e-15] = 0.0
        arr[np.abs(np.abs(arr) - 1.0) < 1e-15] = np.sign(arr[np.abs(np.abs(arr) - 1.0) < 1e-15])
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def check_pair(local: Band, global_: Band) -> float:
    """The grids' common resolution (m); EstimationError if they differ or an origin is not
    finite."""
    r = float(global_.resolution_m)
    if abs(float(local.resolution_m) - r) > 1e-9 * r:
        raise EstimationError(
            f"scan grid resolution {local.resolution_m:g} m differs from the map's {r:g} m"
        )
    if not np.isfinite(local.lower_xy).all() or not np.isfinite(global_.lower_xy).all():
        raise EstimationError("grid origins must be finite")
    return r


def frac(value: np.ndarray) -> np.ndarray:
    """Fractional parts in [0, 1), snapped to 0 within round-off."""
    f = np.asarray(value, dtype=float) % 1.0
    return np.where((f < _SNAP) | (f > 1.0 - _SNAP), 0.0, f)


@dataclass(frozen=True)
class Cells:
    """The informative local cells: centres in cells (local frame / r), and their values."""

    u: np.ndarray  # (K, 2) float64, x and y
    w: np.ndarray  # (K,) float64, non-zero


def local_cells(local: Band, metric: Metric) -> Cells:
    """The local grid's cells with occupied or free evidence; EstimationError if it has none."""
    values = match_values(local, metric)
    rows, cols = np.nonzero(values)
    if len(rows) == 0:
        if metric.score == "centred" and np.asarray(local.known, dtype=bool).any():
            raise EstimationError(
                "scan grid's known cells all have the same value: the centred score is 0 at "
                "every pose"
            )
        raise EstimationError("scan grid has no known cell with occupied or free evidence")
    r = float(local.resolution_m)
    origin = np.asarray(local.lower_xy, dtype=float) / r
    u = np.column_stack([origin[0] + cols + 0.5, origin[1] + rows + 0.5])
    return Cells(u=u, w=values[rows, cols])


def pose_lattice(
    local: Band, global_: Band, window_m: tuple[float, float, float, float] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The translation lattice of a search: (x_m (X,), y_m (Y,), s (2,)).

    Translations are ``origin_G + r·(s + m)`` for integer m, with the sub-cell offset s chosen
    so that at θ = 0 local cell centres land on global cell centres. ``window_m`` (x_min, x_max,
    y_min, y_max), half-open, default the global grid's extent, is clipped to that extent.
    """
    r = check_pair(local, global_)
    s = frac(-np.asarray(local.lower_xy, dtype=float) / r)
    x0, x1, y0, y1 = global_.extent()
    if window_m is not None:
        wx0, wx1, wy0, wy1 = (float(v) for v in window_m)
        if not (wx0 < wx1 and wy0 < wy1) or not all(map(math.isfinite, window_m)):
            raise EstimationError(f"search window must be a non-empty rectangle, got {window_m}")
        if wx1 <= x0 or wx0 >= x1 or wy1 <= y0 or wy0 >= y1:
            raise EstimationError(
                f"search window x {wx0:g}…{wx1:g} m, y {wy0:g}…{wy1:g} m lies outside the map "
                f"(x {x0:g}…{x1:g} m, y {y0:g}…{y1:g} m)"
            )
        x0, x1, y0, y1 = max(x0, wx0), min(x1, wx1), max(y0, wy0), min(y1, wy1)
    axes = []
    for k, (lo, hi) in enumerate(((x0, x1), (y0, y1))):
        base = float(global_.lower_xy[k])
        first = math.ceil((lo - base) / r - s[k] - _SNAP)
        last = math.ceil((hi - base) / r - s[k] - _SNAP) - 1
        if last < first:
            raise EstimationError(
                f"search window {window_m} holds no pose at the map's {r:g} m lattice"
            )
        axes.append(base + r * (s[k] + np.arange(first, last + 1)))
    return axes[0], axes[1], s


def lattice_steps(
    x_m: np.ndarray, y_m: np.ndarray, yaw_rad: np.ndarray
) -> tuple[float, float, float]:
    """The lattice's steps along x, y (m) and yaw (rad); 0 along an axis of one value."""

    def step(a: np.ndarray) -> float:
        return float(a[1] - a[0]) if len(a) > 1 else 0.0

    return step(x_m), step(y_m), step(yaw_rad)


def covers_circle(yaw_rad: np.ndarray) -> bool:
    """Whether the yaws step evenly around the whole circle: the yaw axis wraps around."""
    step = lattice_steps(yaw_rad, yaw_rad, yaw_rad)[2]
    return step > 0 and abs(step * len(yaw_rad) - 2.0 * math.pi) < 1e-6
