"""Planar point-to-plane registration of two station clouds, seeded by a search (docs/design.md
§7).

The correlation search finds the right mode of the (x, y, θ) PDF, but on 0.1 m, 1° lattices and
2D bands cut from occupancy grids its best pose is off by a few centimetres typically and by
decimetres where the ceiling band holds little (a bare ceiling, a band cut at different heights
in the two maps). The stations' 3D points hold far more: every wall, pillar and piece of
furniture both saw. :func:`register` refines the search's pose on them — iterative closest
points, the residual of each source point its distance to the tangent plane of its nearest
target point (Chen and Medioni's point-to-plane error), minimised over (x, y, θ) only (the
robots drive on a floor; z, roll and pitch are fixed by the mount).

Clouds (:class:`Cloud`) are voxel-averaged points with normals from the principal axes of their
neighbourhoods. Every point is kept as a source point: the sparse ones (far walls, seen at a
grazing angle or from afar, where no normal fits) are what pins a long room along its axis —
dropping them let the registration slide by decimetres along corridors. Floor and ceiling points
add nothing to a planar pose (their normals are vertical) and cost little.

The answer's covariance is the Gauss-Newton one (σ² (JᵀWJ)⁻¹, σ² from the weighted residuals)
times ``inflation`` — neighbouring points are not independent, so the plain estimate is far too
confident — and floored. In a corridor the Hessian is nearly singular along its axis, and the
covariance says so.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from estimation.errors import EstimationError
from estimation.search.neighbours import NearestSince, PointGrid
from estimation.search.normals import plane_normals

__all__ = ["Cloud", "Registration", "RegistrationParams", "register"]


@dataclass(frozen=True)
class RegistrationParams:
    """How clouds are made and registered. Distances in metres, angles in radians."""

    voxel_m: float = 0.05  # points averaged per voxel of this side
    max_distance_m: float = 0.3  # farthest correspondence (the search's pose is this good)
    inlier_m: float = 0.1  # a source point is an inlier if its nearest target lies this close
    min_inliers: float = 0.5  # share of the overlapping source points that must be inliers
    huber_m: float = 0.05  # residuals beyond this are down-weighted
    iterations: int = 40
    neighbours: int = 20  # per normal
    inflation: float = 100.0  # covariance factor for the correlation of neighbouring points
    min_sigma_m: float = 0.005
    min_sigma_rad: float = math.radians(0.05)


#: A normal is fitted to the neighbours within this many voxels, if at least this many lie there.
_NORMAL_REACH = 6.0
_MIN_NEIGHBOURS = 5
#: A source point's target is the nearest of this many whose normal agrees with its own to this
#: cosine (60°): the two faces of a thin wall or beam, seen from opposite sides, never pair.
_CANDIDATES = 8
_COMPATIBLE = 0.5
#: The first iterations use every this-many-th source point.
_THIN = 3
#: Fewer correspondences than this: no registration.
_MIN_POINTS = 50
#: A registration that ends farther than this many ``max_distance_m`` from its seed is refused.
_MAX_SLIDE = 2.0
#: Converged when an iteration moves the pose by less than this (m, and rad × 1 m).
_STEP_TOLERANCE = 1e-4
#: ... or when it hands the pose back to where it was two iterations before across a step below
#: this: two sets of nearest neighbours trade the pose between them, and it has settled midway
#: (a generated building's scan link, 0.3 mm apart for 30 iterations, was refused as
#: unconverged at 0.0 cm / 0.01° from the truth).
_CYCLE_STEP = 1e-3
#: A direction whose curvature is below this share of the strongest one is one the points
#: hardly constrain (a corridor's axis): the pose may creep along it for every iteration there
#: is. Settled in the others, the registration has converged there and measures nothing along
#: it: its covariance there is at least ``max_distance_m`` (the registration's reach).
_DEGENERATE = 1e-2
#: ... and only when that direction is a shift: its unit vector's yaw part (rad per m) is below
#: this (a corridor's axis has none; a loose turn is never taken as converged).
_SHIFT_YAW = 0.1
#: A source point's nearest target is looked up with the one after it within the reach plus
#: this (m): while the point moves by less than half their gap, it keeps its nearest.
_NEAREST_MARGIN_M = 0.05
#: Source points farther than ``max_distance_m`` plus this from every target point at some pose
#: are not looked up again until the pose has moved a point by more than this (m).
_OVERLAP_MARGIN_M = 0.15


@dataclass(frozen=True, eq=False)
class Cloud:
    """Points (N, 3) in a robot frame with unit normals (N, 3): the registrable part of a
    station's sweeps."""

    points: np.ndarray
    normals: np.ndarray
    oriented: bool = False  # normals face the side their surface was seen from

    def __len__(self) -> int:
        return len(self.points)

    @functools.cached_property
    def grid(self) -> PointGrid:
        return PointGrid(self.points)

    @classmethod
    def of(
        cls, points: np.ndarray, params: RegistrationParams, viewpoints: np.ndarray | None = None
    ) -> Cloud:
        """The cloud of raw points (N, 3): averaged per voxel, with normals. ``viewpoints``
        (N, 3): where each point was seen from (its scanner); the normals then face the side
        that was seen, so that the two faces of a thin wall or beam are told apart. Non-finite
        points are dropped."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        finite = np.isfinite(points).all(axis=1)
        if viewpoints is not None:
            viewpoints = np.asarray(viewpoints, dtype=np.float64).reshape(-1, 3)
            if len(viewpoints) != len(points):
                raise EstimationError(f"cloud: {len(viewpoints)} viewpoints for "
                                      f"{len(points)} points")  # fmt: skip
            finite &= np.isfinite(viewpoints).all(axis=1)
            viewpoints = viewpoints[finite]
        points = points[finite]
        if len(points) < params.neighbours:
            return cls.empty()
        _, inverse, counts = np.unique(
            _voxel_keys(points, params.voxel_m), return_inverse=True, return_counts=True
        )
        inverse = inverse.reshape(-1)
        centres = _means(points, inverse, counts)
        if len(centres) < params.neighbours:
            return cls.empty()
        grid = PointGrid(centres)
        normals = _normals(centres, params, grid)
        if viewpoints is not None:
            towards = _means(viewpoints, inverse, counts) - centres
            normals *= np.where((normals * towards).sum(axis=1) < 0.0, -1.0, 1.0)[:, None]
        cloud = cls(centres, normals, oriented=viewpoints is not None)
        cloud.__dict__["grid"] = grid  # the normals' grid, on the same points: not built again
        return cloud

    @classmethod
    def empty(cls) -> Cloud:
        return cls(np.zeros((0, 3)), np.zeros((0, 3)))

    def moved(self, pose: np.ndarray) -> Cloud:
        """The cloud in the frame in which its own frame has the planar ``pose`` (x, y, yaw)."""
        turned = _moved(self.normals, np.array([0.0, 0.0, pose[2]]))
        return Cloud(_moved(self.points, pose), turned, self.oriented)

    def thinned(self, every: int) -> Cloud:
        """Every ``every``-th point."""
        return Cloud(self.points[::every], self.normals[::every], self.oriented)

    def reach_m(self) -> float:
        """How far from the frame's origin (in the plane) the points lie, at most."""
        if not len(self):
            return 0.0
        return float(np.sqrt((self.points[:, :2] ** 2).sum(axis=1).max()))

    def within(self, centre_xy: np.ndarray, radius_m: float) -> Cloud:
        """The points within ``radius_m`` of ``centre_xy`` in the plane."""
        keep = ((self.points[:, :2] - centre_xy) ** 2).sum(axis=1) <= radius_m**2
        return Cloud(self.points[keep], self.normals[keep], self.oriented)

    @classmethod
    def joined(cls, clouds: list[Cloud]) -> Cloud:
        if not clouds:
            return cls.empty()
        return cls(np.vstack([c.points for c in clouds]), np.vstack([c.normals for c in clouds]),
                   all(c.oriented for c in clouds))  # fmt: skip


def _voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One int64 per point naming its voxel (the cells' indices from their minimum, packed
    21 bits each: unique over 2 million voxels a side)."""
    cells = np.floor(points / voxel_m).astype(np.int64)
    cells -= cells.min(axis=0)
    if cells.max() >= 1 << 21:
        raise EstimationError(f"cloud spans over {(1 << 21) * voxel_m:.0f} m")
    return (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]


def _means(values: np.ndarray, inverse: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(M, 3) the mean of ``values`` (N, 3) per group (``inverse``: each row's group). Summed
    column by column in the rows' order (``np.add.at`` gives the same sums, 20× slower)."""
    means = np.empty((len(counts), 3))
    for axis in range(3):
        means[:, axis] = np.bincount(inverse, weights=values[:, axis], minlength=len(counts))
    means /= counts[:, None]
    return means


def _normals(points: np.ndarray, params: RegistrationParams,
             grid: PointGrid | None = None) -> np.ndarray:  # fmt: skip
    """Unit normals (N, 3) from the principal axes of each point's nearest neighbours within
    ``_NORMAL_REACH`` voxels; zero where fewer than ``_MIN_NEIGHBOURS`` lie that close (such a
    point is still matched as a source point, but no source point is matched to it)."""
    reach = _NORMAL_REACH * params.voxel_m
    k = min(params.neighbours, len(points))
    index = (PointGrid(points) if grid is None else grid).query(points, k, reach)
    normals = np.zeros_like(points)
    plane_normals(points, index, _MIN_NEIGHBOURS, normals)
    return normals


@dataclass(frozen=True)
class Registration:
    """The refined pose of the source cloud's frame in the target's, its covariance (x, y, yaw
    in the target frame), the share of the overlapping source points (a target within
    ``max_distance_m``) that lie within ``inlier_m`` of one — stations overlap only in part, so
    the share of all source points would say more about the overlap than about the fit —, the
    RMS point-to-plane residual of those inliers, and the iterations taken."""

    pose: np.ndarray  # (3,)
    covariance: np.ndarray  # (3, 3)
    inliers: float
    rms_m: float
    iterations: int
    converged: bool
    inlier_points: int = 0  # source points within ``inlier_m`` of a target
    moved_m: float = 0.0  # how far (in the plane) the pose ended from its seed
    creeping: bool = False  # converged but along one direction the points do not hold it

    def accepted(self, params: RegistrationParams) -> bool:
        """Converged, with enough inliers, and not slid away from its seed: the seed is good to
        ``max_distance_m``, and a pose that ends more than twice that far from it slid along a
        direction the points hardly constrain (a corridor's axis: a scan link slid 66 cm from
        its search's pose and put a pivot 22 cm off) instead of settling on the overlap."""
        return (
            self.converged
            and self.inliers >= params.min_inliers
            and self.moved_m <= _MAX_SLIDE * params.max_distance_m
        )


def register(
    source: Cloud,
    target: Cloud,
    seed: np.ndarray,
    params: RegistrationParams,
    prior: np.ndarray | None = None,
) -> Registration | None:
    """The pose (x, y, yaw) of ``source``'s frame in ``target``'s that lays the source points on
    the target's surfaces, starting from ``seed``; None when too few points correspond.

    ``prior`` (3, 3): the seed's covariance (the search's). The registration then minimises the
    points' residuals plus the seed's Mahalanobis term, so where the points hardly constrain
    the pose — along a corridor without features — it stays with the seed instead of sliding
    (measured: 31 cm along office_loop's corridor without it), and the answer's covariance
    holds both."""
    seed = np.asarray(seed, dtype=np.float64)
    if seed.shape != (3,) or not np.isfinite(seed).all():
        raise EstimationError(f"registration seed must be 3 finite numbers, got {seed!r}")
    information = np.zeros((3, 3)) if prior is None else _inverse_covariance(prior)
    if len(source) < _MIN_POINTS or len(target) < _MIN_POINTS:
        return None
    lookup = _Near(target, params.max_distance_m)
    pose = seed.copy()
    converged = creeping = False
    iterations = 0
    # While iterating, residuals count with the Huber scale as their sigma (the measured one is
    # known only once aligned; before, it would let the seed hold the pose back).
    scale = params.huber_m**2 * params.inflation
    # A third of the source points brings the pose to its basin; all of them finish it.
    thin = [source.thinned(_THIN)] if len(source) >= _THIN * _MIN_POINTS else []
    stages = [(points, params.max_distance_m) for points in [*thin, source]]
    # Last, only the points whose match lies within ``inlier_m``: the Huber weights leave every
    # farther match the pull of one at ``huber_m``, and the points that overlap nothing true
    # (a surface only one station saw, matched to a neighbouring one) pulled links by
    # centimetres.
    stages.append((source, params.inlier_m))
    limit = _MAX_SLIDE * params.max_distance_m
    for points, reach in stages:
        # Convergence is the last stage's; creeping in any stage says the points hardly hold
        # that direction (reset per stage, office_loop's ATE went from 0.8 to 1.3 cm).
        converged = False
        before = None  # the pose two iterations back
        while iterations < params.iterations:
            iterations += 1
            found = _linearised(points, target, lookup, pose, reach, params)
            if found is None:
                return None
            H, g, _, _ = found
            offset = _offset(pose, seed)
            system = H / scale + information + 1e-9 * np.eye(3)
            try:
                step = -np.linalg.solve(system, g / scale + information @ offset)
            except np.linalg.LinAlgError:
                return None
            previous, pose = pose, pose + step
            pose[2] = math.remainder(pose[2], 2 * math.pi)
            if math.hypot(pose[0] - seed[0], pose[1] - seed[1]) > limit:
                break  # it slid: refused however it ends (office_loop: 6 of 45, 40 iterations)
            if max(abs(step[0]), abs(step[1]), abs(step[2])) < _STEP_TOLERANCE:
                converged = True
                break
            if before is not None and _cycled(pose, before, step):
                pose = previous + 0.5 * _offset(pose, previous)
                pose[2] = math.remainder(pose[2], 2 * math.pi)
                converged = True
                break
            before = previous
            if _creeping(system, step):
                converged = creeping = True
                break
        if not converged:
            break
    overlapping = _linearised(source, target, lookup, pose, params.max_distance_m, params)
    final = _linearised(source, target, lookup, pose, params.inlier_m, params)
    if overlapping is None or final is None:
        return None
    near = overlapping[2]
    H, _, residuals, weights = final
    inliers = len(residuals) / len(near)
    dof = max(float(weights.sum()) - 3.0, 1.0)
    sigma2 = max(float((weights * residuals**2).sum()) / dof, 1e-10)
    base = float((residuals**2).sum()) + (len(source) - len(residuals)) * params.inlier_m**2
    H = _profiled(H, source, target, lookup, pose, params, sigma2, base)
    try:
        covariance = np.linalg.inv(H / (sigma2 * params.inflation) + information)
    except np.linalg.LinAlgError:
        return None
    covariance = 0.5 * (covariance + covariance.T)
    floor = np.diag([params.min_sigma_m**2, params.min_sigma_m**2, params.min_sigma_rad**2])
    covariance = _floored(covariance, floor)
    if creeping:
        covariance = _unmeasured(covariance, H, params.max_distance_m)
    rms = math.sqrt(float(np.mean(residuals**2)))
    moved = math.hypot(pose[0] - seed[0], pose[1] - seed[1])
    return Registration(pose, covariance, inliers, rms, iterations, converged, len(residuals),
                        moved, creeping)  # fmt: skip


def _cycled(pose: np.ndarray, before: np.ndarray, step: np.ndarray) -> bool:
    """The step (below ``_CYCLE_STEP``) took the pose back to where it was two iterations
    before (within ``_STEP_TOLERANCE``): a limit cycle between two sets of matches."""
    back = _offset(pose, before)
    return bool(np.abs(back).max() < _STEP_TOLERANCE and np.abs(step).max() < _CYCLE_STEP)


def _creeping(system: np.ndarray, step: np.ndarray) -> bool:
    """The step is below the tolerance along every direction of ``system`` but its weakest,
    which ``system`` hardly constrains (``_DEGENERATE``) and which is a shift in the plane, not
    a turn (its yaw part below ``_SHIFT_YAW``, rad per m): the pose only creeps along that. A
    turn the points hold so loosely is no heading to measure; such a registration goes on."""
    values, vectors = np.linalg.eigh(system)
    if values[0] > _DEGENERATE * values[-1] or abs(vectors[2, 0]) > _SHIFT_YAW:
        return False
    return bool(np.all(np.abs(vectors[:, 1:].T @ step) < _STEP_TOLERANCE))


def _unmeasured(covariance: np.ndarray, H: np.ndarray, sigma_m: float) -> np.ndarray:
    """``covariance`` with a standard deviation of at least ``sigma_m`` along the horizontal
    direction ``H`` constrains least (a rank-one addition: it stays positive definite)."""
    _, vectors = np.linalg.eigh(H[:2, :2])
    u = np.array([vectors[0, 0], vectors[1, 0], 0.0])
    short = sigma_m**2 - float(u @ covariance @ u)
    return covariance + short * np.outer(u, u) if short > 0 else covariance


def _profiled(
    H: np.ndarray,
    source: Cloud,
    target: Cloud,
    lookup: _Near,
    pose: np.ndarray,
    params: RegistrationParams,
    sigma2: float,
    base: float,
) -> np.ndarray:
    """The Gauss-Newton matrix ``H`` with its curvature along its weakest horizontal direction
    lowered to the one measured: the clouds' truncated cost (each source point's squared
    residual, at most ``inlier_m``²; ``inlier_m``² for a point without a match) at shifts of
    ±``inlier_m``/2 along that direction. Along a corridor the Gauss-Newton
    matrix counts the few points that say something about the axis (a pillar, the end of what
    one station saw) as if they pinned it; the shifted clouds show how little they do. A flat
    profile leaves a sigma of ``max_distance_m`` along it (the registration's reach). ``base``:
    the cost at ``pose``."""
    values, vectors = np.linalg.eigh(H[:2, :2])
    u = vectors[:, 0]
    reach = params.inlier_m

    def cost(at: np.ndarray) -> float:
        index, ok = _matches(source, target, lookup, at, reach)
        _, _, residual, _ = _system(source, target, index, ok, at, params.huber_m)
        unmatched = len(source) - len(residual)
        return float(np.minimum(residual**2, reach**2).sum()) + unmatched * reach**2

    shifts = np.array([-0.5, 0.5]) * reach
    rises = np.array([cost(pose + np.array([s * u[0], s * u[1], 0.0])) - base for s in shifts])
    flattest = sigma2 * params.inflation / params.max_distance_m**2
    curvature = max(float((shifts**2 * rises).sum() / (shifts**4).sum()), flattest)
    if curvature >= values[0] or values[0] <= 0:
        return H
    # Scale u's row and column (a congruence keeps H positive semi-definite, its coupling to
    # yaw included) so that its curvature along u is the measured one.
    D = np.eye(3)
    D[:2, :2] += (math.sqrt(curvature / values[0]) - 1.0) * np.outer(u, u)
    return D @ H @ D


def _offset(pose: np.ndarray, seed: np.ndarray) -> np.ndarray:
    offset = pose - seed
    offset[2] = math.remainder(float(offset[2]), 2 * math.pi)
    return offset


def _inverse_covariance(covariance: np.ndarray) -> np.ndarray:
    covariance = np.asarray(covariance, dtype=np.float64)
    if covariance.shape != (3, 3) or not np.isfinite(covariance).all():
        raise EstimationError(f"registration prior must be a finite 3x3 covariance, got "
                              f"{covariance!r}")  # fmt: skip
    try:
        information = np.linalg.inv(0.5 * (covariance + covariance.T))
        np.linalg.cholesky(information)
    except np.linalg.LinAlgError:
        raise EstimationError("registration prior must be positive definite") from None
    return information


def _linearised(
    source: Cloud,
    target: Cloud,
    lookup: _Near,
    pose: np.ndarray,
    reach_m: float,
    params: RegistrationParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The Gauss-Newton system (H, g) of the point-to-plane residuals at ``pose`` over the source
    points with a target within ``reach_m``, their residuals and Huber weights."""
    index, ok = _matches(source, target, lookup, pose, reach_m)
    if ok.sum() < _MIN_POINTS:
        return None
    return _system(source, target, index, ok, pose, params.huber_m)


def _system(
    source: Cloud, target: Cloud, index: np.ndarray, ok: np.ndarray, pose: np.ndarray,
    huber_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """(H, g, residuals, Huber weights) of the matched source points (``ok``) at ``pose``."""
    count = int(ok.sum())
    H, g = np.zeros((3, 3)), np.zeros(3)
    residual, weight = np.empty(count), np.empty(count)
    _gauss_newton(source.points, target.points, target.normals, index, ok,
                  float(pose[0]), float(pose[1]), float(pose[2]), huber_m,
                  H, g, residual, weight)  # fmt: skip
    return H, g, residual, weight


@njit(cache=True, nogil=True)
def _gauss_newton(
    points: np.ndarray, targets: np.ndarray, normals: np.ndarray, index: np.ndarray,
    ok: np.ndarray, x: float, y: float, yaw: float, huber_m: float, H: np.ndarray, g: np.ndarray,
    residuals: np.ndarray, weights: np.ndarray,
) -> None:  # fmt: skip
    """Accumulates Jᵀ W J into ``H`` and Jᵀ W r into ``g`` over the source ``points`` moved by
    (x, y, yaw) and matched (``ok``) to ``targets[index]``: r the distance to the target's
    tangent plane, W the Huber weight; writes r and W in order of the matched points."""
    c, s = math.cos(yaw), math.sin(yaw)
    row = 0
    for i in range(len(points)):
        if not ok[i]:
            continue
        px, py = points[i, 0], points[i, 1]
        t = index[i]
        nx, ny, nz = normals[t, 0], normals[t, 1], normals[t, 2]
        r = ((c * px - s * py + x - targets[t, 0]) * nx
             + (s * px + c * py + y - targets[t, 1]) * ny
             + (points[i, 2] - targets[t, 2]) * nz)  # fmt: skip
        j2 = nx * (-s * px - c * py) + ny * (c * px - s * py)
        size = abs(r)
        w = 1.0 if size <= huber_m else huber_m / max(size, 1e-12)
        J = (nx, ny, j2)
        for a in range(3):
            g[a] += J[a] * w * r
            for b in range(3):
                H[a, b] += J[a] * w * J[b]
        residuals[row] = r
        weights[row] = w
        row += 1


class _Near:
    """The target's :class:`PointGrid`, and for each source cloud the points that may have a
    target within ``reach_m``: at the pose they were last checked at, those with one within
    ``reach_m`` + ``_OVERLAP_MARGIN_M``; checked again once the pose has moved some source point
    by more than the margin. Most of a station's points overlap nothing of the other's (two
    thirds on office_loop), and each iteration would look each of them up again."""

    def __init__(self, target: Cloud, reach_m: float) -> None:
        self.grid = target.grid
        self.reach_m = reach_m
        self._checked: dict[int, tuple[Cloud, float, np.ndarray, np.ndarray]] = {}
        self._nearest: dict[tuple[int, float], tuple[Cloud, NearestSince]] = {}

    def nearest(self, source: Cloud, rows: np.ndarray, moved: np.ndarray,
                reach_m: float) -> np.ndarray:  # fmt: skip
        """(R,) the target nearest to each of ``source``'s points ``rows`` (now at ``moved``)
        within ``reach_m``, ``len(target)`` where none (:class:`NearestSince`)."""
        key = (id(source), reach_m)
        memo = self._nearest.get(key)
        if memo is None:
            memo = (source, NearestSince(self.grid, len(source), reach_m, _NEAREST_MARGIN_M))
            self._nearest[key] = memo
        return memo[1].query(rows, moved)

    def rows(self, source: Cloud, pose: np.ndarray) -> np.ndarray:
        """Indices of ``source``'s points that may have a target within ``reach_m`` at ``pose``
        (:func:`_matches` looks every point up for a larger reach)."""
        checked = self._checked.get(id(source))
        if checked is not None:
            _, radius, at, rows = checked
            turn = abs(math.remainder(float(pose[2] - at[2]), 2 * math.pi))
            if math.hypot(pose[0] - at[0], pose[1] - at[1]) + turn * radius <= _OVERLAP_MARGIN_M:
                return rows
        near = self.grid.any_within(_moved(source.points, pose), self.reach_m + _OVERLAP_MARGIN_M)
        rows = np.flatnonzero(near)
        self._checked[id(source)] = (source, source.reach_m(), np.array(pose, dtype=float), rows)
        return rows


def _moved(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """``points`` (N, 3) moved by the planar ``pose``."""
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    return np.c_[c * points[:, 0] - s * points[:, 1] + pose[0],
                 s * points[:, 0] + c * points[:, 1] + pose[1], points[:, 2]]  # fmt: skip


def _matches(
    source: Cloud, target: Cloud, lookup: _Near, pose: np.ndarray, reach_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each source point's target at ``pose``: the nearest of its ``_CANDIDATES`` nearest
    within ``reach_m`` that has a normal facing the same way as its own (within 60°; either way
    when the clouds' normals are not oriented; any with a normal when the source point has none).
    Returns the targets' indices and whether one was found. The nearest target is tried first
    for every point; the further candidates are looked up only for the points it does not
    suit."""
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    rows = lookup.rows(source, pose) if reach_m <= lookup.reach_m else np.arange(len(source))
    moved = _moved(source.points[rows], pose)
    oriented = source.oriented and target.oriented
    nearest = lookup.nearest(source, rows, moved, reach_m)[:, None]
    index, ok = np.zeros(len(source), dtype=np.int64), np.zeros(len(source), dtype=bool)
    _pick(nearest, rows, target.normals, source.normals, c, s, oriented, index, ok)
    retry = np.flatnonzero((nearest[:, 0] < len(target)) & ~ok[rows])
    k = min(_CANDIDATES, len(target))
    if len(retry) and k > 1:
        candidates = lookup.grid.query(moved[retry], k, reach_m)
        _pick(candidates, rows[retry], target.normals, source.normals, c, s, oriented, index, ok)
    return index, ok


@njit(cache=True, nogil=True)
def _pick(
    candidates: np.ndarray, rows: np.ndarray, target_normals: np.ndarray,
    source_normals: np.ndarray, c: float, s: float, oriented: bool, index: np.ndarray,
    ok: np.ndarray,
) -> None:  # fmt: skip
    """For source point ``rows[r]`` (its normal turned by the yaw's cosine and sine): the first
    of ``candidates[r]`` (a :class:`PointGrid` answer, nearest first, ``len(target_normals)``
    where none) that may pair with it into ``index``, and ``ok``; the nearest (or 0) and False
    when none may. A target may pair when it has a normal and the two normals agree within 60°
    (facing the same way when ``oriented``), or when the source point has no normal."""
    n = len(target_normals)
    for r in range(len(rows)):
        i = rows[r]
        sx, sy, sz = source_normals[i, 0], source_normals[i, 1], source_normals[i, 2]
        tx, ty = c * sx - s * sy, s * sx + c * sy
        unnormed = sx * sx + sy * sy + sz * sz < 0.5
        first = candidates[r, 0]
        index[i], ok[i] = first if first < n else 0, False
        for j in range(candidates.shape[1]):
            t = candidates[r, j]
            if t >= n:
                break
            nx, ny, nz = target_normals[t, 0], target_normals[t, 1], target_normals[t, 2]
            if nx * nx + ny * ny + nz * nz <= 0.5:
                continue
            agree = nx * tx + ny * ty + nz * sz
            if not oriented:
                agree = abs(agree)
            if agree >= _COMPATIBLE or unnormed:
                index[i], ok[i] = t, True
                break


def _floored(covariance: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """The covariance with every direction at least as uncertain as ``floor`` says (eigenvalues
    of the whitened matrix raised to 1)."""
    L = np.linalg.cholesky(floor)
    L_inv = np.linalg.inv(L)
    whitened = L_inv @ covariance @ L_inv.T
    values, vectors = np.linalg.eigh(0.5 * (whitened + whitened.T))
    values = np.maximum(values, 1.0)
    return L @ (vectors * values) @ vectors.T @ L.T
