"""Calibration of the rotating mirror from sweeps of a static, planar scene (docs/calibration.md).

Two groups of parameters place the scan plane (docs/design.md §3):

* **Phase.** φ = 2ψ + φ0, with ψ = 0 at the edge-on moment. A wrong ``edge_on_motor_phase``
  moves the edge-on moment, and so every φ of a sweep, by −Δp / (gear_ratio / 2) (Δp wrapped to
  half a motor turn); a wrong φ0 moves every φ by Δφ0. The scene cannot tell the two apart, but
  the timing can: the edge-on signature, timed against the blocking arm, gives the motor phase at
  the edge-on moment directly (:func:`edge_on_motor_phase`). With that phase fixed, the scene
  gives φ0, which then also absorbs what error is left in the phase.
* **Axis offset d** (paper eq. 4, corrected): x = d + (r cos θ − d) cos φ, z = (r cos θ − d) sin φ.
  A wrong d bends planes: Δx = Δd (1 − cos φ), Δz = −Δd sin φ.

:func:`fit_mirror` estimates d and the elevation correction δ (added to φ0) from sweeps taken
while the robot stood still on a level floor. Points are re-projected with candidate (d, δ):
a coarse grid search scores the floor alone (z = −scanner height in the scanner frame, a
truncated quadratic); then the planes of the scene are found (the floor, then RANSAC planes,
each classed as horizontal, vertical or oblique), and a robust least-squares fit minimises the
point-to-plane distances with the planes re-fitted at every step (variable projection),
re-segmenting until the estimate settles. The floor's known height anchors δ: a rotation about
the mirror axis leaves free planes planar, so without the floor only the level structure
(horizontal ceilings, vertical walls) constrains it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from sensors.errors import SensorError
from sensors.scan3d.mirror import MirrorEstimate, mirror_points

__all__ = [
    "MirrorCalibration",
    "MirrorFitSettings",
    "PhaseEstimate",
    "SweepSamples",
    "edge_on_motor_phase",
    "fit_mirror",
]

FLOOR, HORIZONTAL, VERTICAL, OBLIQUE = 0, 1, 2, 3
#: A plane's normal within this angle of vertical (horizontal) makes it a horizontal (vertical)
#: plane; level structure is assumed exactly level.
LEVEL_TOLERANCE_RAD = math.radians(5.0)


@dataclass(frozen=True)
class PhaseEstimate:
    """The motor phase at the edge-on moment, from the arm and the edge-on signature."""

    phase_rad: float  # in [0, 2π): the value of ``edge_on_motor_phase``
    spread_rad: float  # circular standard deviation over the dwells
    dwells: int


def edge_on_motor_phase(estimates: Sequence[MirrorEstimate]) -> PhaseEstimate:
    """Circular mean, over dwells, of the motor phase at the coarse edge-on moment.

    Each estimate must come from :func:`~sensors.scan3d.mirror.estimate_mirror` without a
    calibrated phase (``edge_on_motor_phase_rad=None``), so that its edge-on time is the
    signature's own.
    """
    if not estimates:
        raise SensorError("no dwell with arm edges and an edge-on signature: the phase is unknown")
    if any(e.fine_phase for e in estimates):
        raise SensorError("the edge-on phase needs coarse mirror estimates (no calibrated phase)")
    turns = np.array(
        [(e.edge_on_time_s - e.motor_phase_time_s) / e.motor_period_s for e in estimates]
    )
    unit = np.exp(2j * math.pi * turns)
    mean = complex(np.mean(unit))
    if abs(mean) < 1e-6:
        raise SensorError("the edge-on signatures disagree on the motor phase: no consensus")
    spread = math.sqrt(max(0.0, -2.0 * math.log(min(1.0, abs(mean)))))
    return PhaseEstimate(float(np.angle(mean)) % (2 * math.pi), spread, len(estimates))


@dataclass(frozen=True)
class SweepSamples:
    """The polar samples of one sweep, with the elevations the sweep was assembled with.

    ``start_shift_rad`` is what the starting calibration adds to those elevations (its edge-on
    moment differs when its motor phase does); it only enters the "before" residual.
    """

    range_m: np.ndarray  # (N,)
    bearing_rad: np.ndarray  # (N,)
    elevation_rad: np.ndarray  # (N,)
    start_shift_rad: float = 0.0


@dataclass(frozen=True)
class MirrorFitSettings:
    """How :func:`fit_mirror` works; lengths in metres, angles in radians."""

    scanner_height_m: float  # the floor lies at z = −this in the scanner frame
    scanner_x_m: float = 0.1  # scanner origin ahead of the robot origin
    exclude_radius_m: float = 0.4  # returns this close to the robot origin (the robot) are left out
    max_points_per_sweep: int = 3000
    axis_search_m: float = 0.05  # the coarse search spans d ± this
    elevation_search_rad: float = math.radians(10.0)  # and δ ± this
    inlier_m: float = 0.02  # a point belongs to a plane within this
    min_plane_points: int = 120
    max_planes: int = 10  # per sweep, besides the floor
    ransac_iterations: int = 200
    warn_sigma_axis_m: float = 0.5e-3
    warn_sigma_elevation_rad: float = math.radians(0.03)
    seed: int = 0


@dataclass(frozen=True)
class MirrorCalibration:
    """The estimate, its residuals and how well the scene constrained it."""

    axis_offset_m: float
    elevation_correction_rad: float  # add to φ0
    start_axis_offset_m: float
    rms_before_m: float  # point-to-plane, the starting calibration
    rms_after_m: float
    sweeps: int
    points: int  # points on planes in the final fit
    floor_points: int
    planes: dict[str, int]  # planes per class, over all sweeps
    sigma_axis_offset_m: float  # formal standard errors
    sigma_elevation_rad: float
    correlation: float
    warnings: tuple[str, ...]


@dataclass(frozen=True)
class _Cloud:
    range_m: np.ndarray
    bearing_rad: np.ndarray
    elevation_rad: np.ndarray
    start_shift_rad: np.ndarray  # per point
    sweep: np.ndarray  # per point

    def points(self, axis_offset_m: float, correction_rad: float | np.ndarray) -> np.ndarray:
        return mirror_points(
            self.range_m, self.bearing_rad, self.elevation_rad + correction_rad, axis_offset_m
        )


@dataclass(frozen=True)
class _Segmentation:
    order: np.ndarray  # point indices grouped by plane
    bounds: np.ndarray  # plane k holds order[bounds[k]:bounds[k + 1]]
    kinds: np.ndarray  # class of each plane (FLOOR, HORIZONTAL, VERTICAL, OBLIQUE)
    normals: np.ndarray  # (planes, 3) each plane's normal when found: orients the re-fitted ones

    @property
    def points(self) -> int:
        return int(self.bounds[-1])


def _cloud(sweeps: Sequence[SweepSamples], axis_offset_m: float, settings: MirrorFitSettings,
           rng: np.random.Generator) -> _Cloud:  # fmt: skip
    parts: list[tuple[np.ndarray, ...]] = []
    for k, sweep in enumerate(sweeps):
        r, b, e = (np.asarray(a, dtype=float) for a in (sweep.range_m, sweep.bearing_rad,
                                                          sweep.elevation_rad))  # fmt: skip
        if not (r.shape == b.shape == e.shape and r.ndim == 1):
            raise SensorError(f"sweep {k}: range, bearing and elevation must be equal-length 1-D")
        if not math.isfinite(sweep.start_shift_rad):
            raise SensorError(f"sweep {k}: the start shift is not finite")
        keep = np.isfinite(r) & np.isfinite(b) & np.isfinite(e) & (r > 0)
        p = mirror_points(r, b, e + sweep.start_shift_rad, axis_offset_m)
        keep &= np.hypot(p[:, 0] + settings.scanner_x_m, p[:, 1]) > settings.exclude_radius_m
        rows = np.flatnonzero(keep)
        if len(rows) > settings.max_points_per_sweep:
            rows = np.sort(rng.choice(rows, settings.max_points_per_sweep, replace=False))
        n = len(rows)
        parts.append((r[rows], b[rows], e[rows], np.full(n, sweep.start_shift_rad), np.full(n, k)))
    r, b, e, shift, which = (np.concatenate([p[i] for p in parts]) for i in range(5))
    return _Cloud(r, b, e, shift, which.astype(np.int64))


def _floor_search(cloud: _Cloud, h: float, axes: np.ndarray, corrections: np.ndarray,
                  band_m: float) -> tuple[float, float]:  # fmt: skip
    """The (d, δ) on a grid that brings the most returns onto the floor (truncated quadratic)."""
    down = cloud.elevation_rad < 0
    folded = cloud.range_m[down] * np.cos(cloud.bearing_rad[down])
    sin_e, cos_e = np.sin(cloud.elevation_rad[down]), np.cos(cloud.elevation_rad[down])
    sin_e_d = sin_e[:, None] * np.cos(corrections)[None, :] + cos_e[:, None] * np.sin(corrections)
    best = (math.inf, float(axes[0]), float(corrections[0]))
    for d in axes:
        z = (folded - d)[:, None] * sin_e_d + h
        cost = np.minimum(z**2, band_m**2).sum(axis=0)
        k = int(np.argmin(cost))
        if cost[k] < best[0]:
            best = (float(cost[k]), float(d), float(corrections[k]))
    return best[1], best[2]


def _kind(normal: np.ndarray) -> int:
    vertical_component = abs(float(normal[2]))
    if vertical_component > math.cos(LEVEL_TOLERANCE_RAD):
        return HORIZONTAL
    if vertical_component < math.sin(LEVEL_TOLERANCE_RAD):
        return VERTICAL
    return OBLIQUE


def _pca_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    normal = vt[-1]
    return normal, float(normal @ centre)


def _ransac(points: np.ndarray, settings: MirrorFitSettings, rng: np.random.Generator,
            tolerance_m: float) -> list[tuple[np.ndarray, int, np.ndarray]]:  # fmt: skip
    """Planes found one after another among ``points``: (member indices, class, normal) each."""
    remaining = np.arange(len(points))
    found: list[tuple[np.ndarray, int, np.ndarray]] = []
    while len(found) < settings.max_planes and len(remaining) >= settings.min_plane_points:
        p = points[remaining]
        picks = rng.integers(0, len(p), (settings.ransac_iterations, 3))
        a, b, c = p[picks[:, 0]], p[picks[:, 1]], p[picks[:, 2]]
        normals = np.cross(b - a, c - a)
        norms = np.linalg.norm(normals, axis=1)
        ok = norms > 1e-6
        if not ok.any():
            break
        normals = normals[ok] / norms[ok, None]
        offsets = np.einsum("ij,ij->i", normals, a[ok])
        counts = (np.abs(p @ normals.T - offsets) < tolerance_m).sum(axis=0)
        k = int(np.argmax(counts))
        members = np.abs(p @ normals[k] - offsets[k]) < tolerance_m
        if members.sum() < settings.min_plane_points:
            break
        normal, offset = _pca_plane(p[members])
        members = np.abs(p @ normal - offset) < tolerance_m
        if members.sum() < settings.min_plane_points:
            break
        found.append((remaining[members], _kind(normal), normal))
        remaining = remaining[~members]
    return found


def _segment(cloud: _Cloud, d: float, correction: float, settings: MirrorFitSettings,
             tolerance_m: float) -> _Segmentation:  # fmt: skip
    """Assign points to the floor and to each sweep's other planes at (d, δ)."""
    rng = np.random.default_rng([settings.seed, 1])
    points = cloud.points(d, correction)
    on_floor = np.abs(points[:, 2] + settings.scanner_height_m) < tolerance_m
    groups: list[np.ndarray] = [np.flatnonzero(on_floor)]
    kinds = [FLOOR]
    normals = [np.array([0.0, 0.0, 1.0])]
    for sweep in np.unique(cloud.sweep):
        rows = np.flatnonzero((cloud.sweep == sweep) & ~on_floor)
        for members, kind, normal in _ransac(points[rows], settings, rng, tolerance_m):
            groups.append(rows[members])
            kinds.append(kind)
            normals.append(normal)
    bounds = np.concatenate([[0], np.cumsum([len(g) for g in groups])])
    return _Segmentation(np.concatenate(groups), bounds, np.asarray(kinds), np.asarray(normals))


def _residuals(cloud: _Cloud, segmentation: _Segmentation, d: float,
               correction: float | np.ndarray, h: float) -> np.ndarray:  # fmt: skip
    """Point-to-plane distances, each plane re-fitted to its points (the floor is fixed)."""
    order = segmentation.order
    shift = correction[order] if isinstance(correction, np.ndarray) else correction
    p = mirror_points(
        cloud.range_m[order], cloud.bearing_rad[order], cloud.elevation_rad[order] + shift, d
    )
    out = np.empty(len(order))
    for k, kind in enumerate(segmentation.kinds):
        lo, hi = segmentation.bounds[k], segmentation.bounds[k + 1]
        q = p[lo:hi]
        if kind == FLOOR:
            out[lo:hi] = q[:, 2] + h
        elif kind == HORIZONTAL:
            out[lo:hi] = q[:, 2] - q[:, 2].mean()
        elif kind == VERTICAL:
            xy = q[:, :2] - q[:, :2].mean(axis=0)
            _, _, vt = np.linalg.svd(xy, full_matrices=False)
            # The singular vector's sign is arbitrary: keep the side the plane was found with,
            # so that residuals change smoothly with the parameters.
            out[lo:hi] = (xy @ vt[-1]) * np.sign(vt[-1] @ segmentation.normals[k, :2] or 1.0)
        else:
            centred = q - q.mean(axis=0)
            _, _, vt = np.linalg.svd(centred, full_matrices=False)
            out[lo:hi] = (centred @ vt[-1]) * np.sign(vt[-1] @ segmentation.normals[k] or 1.0)
    return out


def _refine(cloud: _Cloud, segmentation: _Segmentation, start: tuple[float, float], h: float,
            scale_m: float) -> tuple[float, float]:  # fmt: skip
    def fun(x: np.ndarray) -> np.ndarray:
        return _residuals(cloud, segmentation, float(x[0]), float(x[1]), h)

    fit = least_squares(
        fun, np.asarray(start), x_scale=np.array([1e-3, 1e-3]), loss="soft_l1", f_scale=scale_m,
        diff_step=1e-7, xtol=1e-10, ftol=1e-12,
    )  # fmt: skip
    return float(fit.x[0]), float(fit.x[1])


def _covariance(cloud: _Cloud, segmentation: _Segmentation, d: float, correction: float,
                h: float) -> np.ndarray:  # fmt: skip
    """Formal covariance of (d, δ): central-difference Jacobian, robust residual scale."""
    step = 1e-5
    jacobian = np.column_stack(
        [
            (_residuals(cloud, segmentation, d + step, correction, h)
             - _residuals(cloud, segmentation, d - step, correction, h)) / (2 * step),
            (_residuals(cloud, segmentation, d, correction + step, h)
             - _residuals(cloud, segmentation, d, correction - step, h)) / (2 * step),
        ]
    )  # fmt: skip
    residual = _residuals(cloud, segmentation, d, correction, h)
    scale = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
    information = jacobian.T @ jacobian
    if np.linalg.cond(information) > 1e14:
        return np.full((2, 2), np.inf)
    return np.asarray(scale**2 * np.linalg.inv(information))


def fit_mirror(
    sweeps: Sequence[SweepSamples], axis_offset_m: float, settings: MirrorFitSettings
) -> MirrorCalibration:
    """Estimate the axis offset d and the elevation correction δ from static sweeps.

    ``axis_offset_m`` is the starting d. The sweeps' elevations hold the starting φ0 (δ = 0);
    the result's δ is to be added to it. Units: metres and radians, scanner frame.
    """
    h = settings.scanner_height_m
    if not sweeps:
        raise SensorError("no sweeps to calibrate the mirror from")
    if not (math.isfinite(axis_offset_m) and axis_offset_m > 0):
        raise SensorError(f"the starting axis offset must be positive, got {axis_offset_m!r}")
    if not (math.isfinite(h) and h > 0):
        raise SensorError(f"the scanner height must be positive, got {h!r}")
    rng = np.random.default_rng(settings.seed)
    cloud = _cloud(sweeps, axis_offset_m, settings, rng)
    if len(cloud.range_m) < 10 * settings.min_plane_points:
        raise SensorError(
            f"only {len(cloud.range_m)} usable returns in {len(sweeps)} sweeps: too few to "
            "calibrate the mirror"
        )
    low = max(0.005, axis_offset_m - settings.axis_search_m)
    span = settings.elevation_search_rad
    d, delta = _floor_search(
        cloud, h, np.arange(low, axis_offset_m + settings.axis_search_m + 1e-9, 0.005),
        np.arange(-span, span + 1e-9, math.radians(0.5)), band_m=0.03,
    )  # fmt: skip
    d, delta = _floor_search(
        cloud, h, np.arange(max(0.005, d - 0.005), d + 0.005 + 1e-9, 0.0005),
        delta + np.radians(np.arange(-0.5, 0.5 + 1e-9, 0.05)), band_m=0.015,
    )  # fmt: skip
    warnings: list[str] = []
    if abs(d - axis_offset_m) > 0.95 * settings.axis_search_m or abs(delta) > 0.95 * span:
        warnings.append(
            "the floor search ended at the edge of its range: the start may be too far off"
        )
    for tolerance in (2 * settings.inlier_m, settings.inlier_m, settings.inlier_m):
        segmentation = _segment(cloud, d, delta, settings, tolerance)
        if segmentation.bounds[1] == 0:
            raise SensorError(
                f"no returns on the floor at {h:g} m below the scanner: the mirror cannot be "
                "calibrated (is robot.scanner_height_m right, and the floor in view?)"
            )
        d, delta = _refine(cloud, segmentation, (d, delta), h, tolerance / 2)
    if not (math.isfinite(d) and math.isfinite(delta)) or d <= 0:
        raise SensorError(f"the mirror fit diverged (d = {d!r}, δ = {delta!r})")
    after = _residuals(cloud, segmentation, d, delta, h)
    before = _residuals(cloud, segmentation, axis_offset_m, cloud.start_shift_rad, h)
    covariance = _covariance(cloud, segmentation, d, delta, h)
    sigma_d, sigma_e = (float(math.sqrt(max(covariance[k, k], 0.0))) for k in (0, 1))
    correlation = (
        float(covariance[0, 1] / (sigma_d * sigma_e))
        if math.isfinite(sigma_d * sigma_e) and sigma_d * sigma_e > 0
        else 1.0
    )
    floor_points = int(segmentation.bounds[1])
    if floor_points < 500:
        warnings.append(
            f"only {floor_points} floor returns: the elevation offset rests on the walls and "
            "ceiling alone"
        )
    if not sigma_d <= settings.warn_sigma_axis_m:
        warnings.append(
            f"the scene constrains the axis offset poorly (σ {sigma_d * 1e3:.2f} mm): record "
            "floor near and far and walls at several distances"
        )
    if not sigma_e <= settings.warn_sigma_elevation_rad:
        warnings.append(
            f"the scene constrains the elevation offset poorly (σ {math.degrees(sigma_e):.3f}°): "
            "record more of the floor"
        )
    if abs(correlation) > 0.98:
        warnings.append(
            f"axis offset and elevation offset are nearly confounded (correlation "
            f"{correlation:+.3f}): record a scene with floor, walls and ceiling"
        )
    names = {FLOOR: "floor", HORIZONTAL: "horizontal", VERTICAL: "vertical", OBLIQUE: "oblique"}
    planes = {name: int(np.count_nonzero(segmentation.kinds == kind))
              for kind, name in names.items()}  # fmt: skip
    return MirrorCalibration(
        axis_offset_m=d,
        elevation_correction_rad=delta,
        start_axis_offset_m=axis_offset_m,
        rms_before_m=float(np.sqrt(np.mean(before**2))),
        rms_after_m=float(np.sqrt(np.mean(after**2))),
        sweeps=len(sweeps),
        points=segmentation.points,
        floor_points=floor_points,
        planes=planes,
        sigma_axis_offset_m=sigma_d,
        sigma_elevation_rad=sigma_e,
        correlation=correlation,
        warnings=tuple(warnings),
    )
