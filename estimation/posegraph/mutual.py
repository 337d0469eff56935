"""Mutual localization of two robots from each other's beacons (paper §2.1, docs/design.md §4).

Robot A sees C's beacon at range ``a`` and bearing ``α`` (A's scanner frame); robot C sees A's
beacon at ``(b, β)`` (C's scanner frame). Each beacon sits ``d`` straight ahead of its robot's
scanner origin. With ``u = a e^{iα}`` and ``v = b e^{iβ}`` (numpy complex numbers):

* paper eq. 1: ``e^{iθ} = (u − d) / (b − d e^{−iβ})``; C's heading is ``θ − β + π``, which
  simplifies to ``arg(u − d) − arg(v − d) + π`` (the beacon-to-beacon direction seen from both);
* paper eq. 2: C's scanner origin in A's scanner frame, ``C = (u v − d²) / (v − d)``;
* the consistency check: ``s1 = |u − d|`` (cosine rule, as seen by A) and ``s2 = |v − d|`` (as
  seen by C) are both the distance between the two beacons.

Everything is in SI units (metres, radians). The vectorised functions take arrays of any common
shape; :func:`relative_pose` and :func:`localize_mutual` are the checked single-event entry points.

Four measurements fix three unknowns, so the closed form is not the most accurate estimate: its
error is up to ~2× the Cramér–Rao bound at short range. :func:`refine_relative_pose` takes it as
the starting point of a Gauss–Newton maximum-likelihood fit of the four raw measurements, which
reaches the bound; the pose graph uses that estimate and its information.
"""

from __future__ import annotations

import cmath
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from estimation.errors import EstimationError
from sensors.geometry.se2 import between, compose, wrap_angle
from sensors.geometry.se2 import inverse as se2_inverse

__all__ = [
    "DEFAULT_MIN_RANGE_M",
    "DEFAULT_MIN_SEPARATION_M",
    "GAP_OUTLIER",
    "GAP_SAMPLES",
    "MAX_GAP_SCALE",
    "MutualFix",
    "check_observation",
    "closed_form",
    "closed_form_jacobian",
    "closure_distance",
    "cramer_rao_bound",
    "gap_scale",
    "gap_sigma",
    "localize_mutual",
    "measurement_jacobian",
    "measurements",
    "refine_relative_pose",
    "relative_pose",
    "separations",
    "sighting_distance",
]

#: Ranges below this are not beacon detections (the LMS's own minimum is 0.05 m).
DEFAULT_MIN_RANGE_M = 0.05
#: Two beacons closer than this: the geometry degenerates (b·e^{iβ} ≈ d).
DEFAULT_MIN_SEPARATION_M = 0.05


def _complex(a_m: np.ndarray, alpha_rad: np.ndarray) -> np.ndarray:
    return np.asarray(a_m, dtype=float) * np.exp(1j * np.asarray(alpha_rad, dtype=float))


def closed_form(
    a_m: np.ndarray | float,
    alpha_rad: np.ndarray | float,
    b_m: np.ndarray | float,
    beta_rad: np.ndarray | float,
    d_m: float,
) -> np.ndarray:
    """(..., 3) poses ``x_m, y_m, yaw_rad`` of C's scanner in A's scanner frame (paper eq. 1–2).

    Unchecked and vectorised; degenerate input gives inf or NaN (see :func:`check_observation`).
    """
    u = _complex(np.asarray(a_m), np.asarray(alpha_rad))
    v = _complex(np.asarray(b_m), np.asarray(beta_rad))
    beta = np.asarray(beta_rad, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        position = (u * v - d_m * d_m) / (v - d_m)  # eq. 2
        e_theta = (u - d_m) / (np.asarray(b_m, dtype=float) - d_m * np.exp(-1j * beta))  # eq. 1
    yaw = wrap_angle(np.angle(e_theta) - beta + np.pi)
    return np.stack(np.broadcast_arrays(position.real, position.imag, yaw), axis=-1)


def closed_form_jacobian(
    a_m: np.ndarray | float,
    alpha_rad: np.ndarray | float,
    b_m: np.ndarray | float,
    beta_rad: np.ndarray | float,
    d_m: float,
) -> np.ndarray:
    """(..., 3, 4) analytic Jacobian of :func:`closed_form` w.r.t. ``(a, α, b, β)``.

    ``∂C/∂u = v / (v − d)``, ``∂C/∂v = −d (u − d) / (v − d)²`` (C is holomorphic in u and v);
    ``∂yaw = Im(∂u / (u − d)) − Im(∂v / (v − d))``.
    """
    alpha = np.asarray(alpha_rad, dtype=float)
    beta = np.asarray(beta_rad, dtype=float)
    u = _complex(np.asarray(a_m), alpha)
    v = _complex(np.asarray(b_m), beta)
    with np.errstate(divide="ignore", invalid="ignore"):
        dC_du = v / (v - d_m)
        dC_dv = -d_m * (u - d_m) / (v - d_m) ** 2
        du = np.stack(np.broadcast_arrays(np.exp(1j * alpha), 1j * u, 0j, 0j), axis=-1)
        dv = np.stack(np.broadcast_arrays(0j, 0j, np.exp(1j * beta), 1j * v), axis=-1)
        dC = dC_du[..., None] * du + dC_dv[..., None] * dv
        dyaw = (du / (u - d_m)[..., None]).imag - (dv / (v - d_m)[..., None]).imag
    return np.stack([dC.real, dC.imag, dyaw], axis=-2)


def _closure(z: np.ndarray, d_m: float) -> np.ndarray:
    """(..., 3) residual of :func:`closure_distance` for stacked measurements z (..., 12)."""
    ac, at, tc = (
        closed_form(z[..., k], z[..., k + 1], z[..., k + 2], z[..., k + 3], d_m) for k in (0, 4, 8)
    )
    return between(ac, compose(at, tc))


def _mahalanobis(
    residual: Callable[[np.ndarray], np.ndarray],
    z: np.ndarray,
    sigmas: np.ndarray,
    angle: int,
) -> np.ndarray:
    """Squared Mahalanobis distances (...,) of ``residual(z)`` (..., m), its covariance the
    measurements' independent noise (``sigmas``, one per column of z) propagated by a numerical
    Jacobian; column ``angle`` of the residual is an angle (its differences wrapped)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        r = residual(z)
        m = r.shape[-1]
        J = np.empty((*z.shape[:-1], m, z.shape[-1]))
        for k in range(z.shape[-1]):
            step = 1e-7 if k % 2 else 1e-6  # columns alternate range, bearing
            moved = z.copy()
            moved[..., k] += step
            change = residual(moved) - r
            change[..., angle] = wrap_angle(change[..., angle])
            J[..., k] = change / step * sigmas[k]
        # A floor far below any measurement's: an exactly singular covariance never raises.
        covariance = J @ np.swapaxes(J, -1, -2) + 1e-12 * np.eye(m)
        return np.einsum("...i,...i->...", r, np.linalg.solve(covariance, r[..., None])[..., 0])


def _stacked(*parts: np.ndarray | Sequence[float]) -> np.ndarray:
    """The measurement vectors side by side (..., n1 + n2 + …), leading axes broadcast."""
    arrays = [np.asarray(v, dtype=float) for v in parts]
    lead = np.broadcast_shapes(*(a.shape[:-1] for a in arrays))
    return np.concatenate([np.broadcast_to(a, (*lead, a.shape[-1])) for a in arrays], axis=-1)


def closure_distance(
    z_ac: np.ndarray,
    z_at: np.ndarray,
    z_tc: np.ndarray,
    d_m: float,
    range_sigma_m: float,
    bearing_sigma_rad: float,
) -> np.ndarray:
    """Squared Mahalanobis distances (...,) of how far three robots' mutual observations fail
    to close: C's pose in A's frame measured directly and through the third robot T.

    Each ``z`` is (..., 4) ``(a, α, b, β)``: ``z_ac`` A sees C's beacon, C sees A's; ``z_at`` A
    sees T's, T sees A's; ``z_tc`` T sees C's, C sees T's. The residual is ``P_AC⁻¹ ∘ P_AT ∘
    P_TC`` of the closed-form poses, its covariance the twelve measurements' noise propagated by
    a numerical Jacobian: χ² with 3 degrees of freedom when the three pairs are what they claim
    to be. Two robots' detections swapped (a third beacon taken for the partner's at the same
    distance) leave a residual of the order of the distances (non-finite for degenerate input).
    """
    sigmas = np.tile([range_sigma_m, bearing_sigma_rad], 6)
    return _mahalanobis(lambda z: _closure(z, d_m), _stacked(z_ac, z_at, z_tc), sigmas, 2)


def _sighting(z: np.ndarray, d_m: float, through: str, observer: int) -> np.ndarray:
    """(..., 2) residual of :func:`sighting_distance` for stacked z (..., 10)."""
    ac, pair = (closed_form(z[..., k], z[..., k + 1], z[..., k + 2], z[..., k + 3], d_m)
                for k in (0, 4))  # fmt: skip
    # T's pose in C's frame (through A) or in A's (through C).
    pose = compose(se2_inverse(ac), pair) if through == "A" else compose(ac, pair)
    predicted = measurements(pose, d_m)[..., 2 * observer : 2 * observer + 2]
    out = z[..., 8:10] - predicted
    out[..., 1] = wrap_angle(out[..., 1])
    return out


def sighting_distance(
    z_ac: np.ndarray,
    z_pair: np.ndarray,
    observed: np.ndarray,
    through: Literal["A", "C"],
    observer: Literal[0, 1],
    d_m: float,
    range_sigma_m: float,
    bearing_sigma_rad: float,
) -> np.ndarray:
    """Squared Mahalanobis distances (...,) of a one-way sighting from where two mutual
    observations place it: the part of a triangle's closure that one missing detection leaves.

    ``z_ac`` (..., 4) is A and C's observation, ``z_pair`` (..., 4) a third robot T's with A
    (``through="A"``: A sees T's beacon, T sees A's) or with C (``"C"``: C sees T's, T sees
    C's). Together they place T against the robot not in the pair — X, C or A — and
    ``observed`` (..., 2) (range, bearing) is checked against X's sighting of T's beacon
    (``observer`` 0) or T's of X's (1). χ² with 2 degrees of freedom when all is what it
    claims to be. Building 106: b saw a's beacon and c's at the same distance, a saw b's and
    not c's, and c saw a's 1.07 m away: through the b–a pair, b's true detection of c puts a's
    beacon 1.07 m from c, the other 0.88 m away and 128° off."""
    sigmas = np.tile([range_sigma_m, bearing_sigma_rad], 5)
    return _mahalanobis(lambda z: _sighting(z, d_m, through, observer),
                        _stacked(z_ac, z_pair, observed), sigmas, 1)  # fmt: skip


def measurements(pose: np.ndarray, d_m: float) -> np.ndarray:
    """(..., 4) noise-free ``(a, α, b, β)`` for poses (..., 3) of C's scanner in A's frame.

    The measurement model the closed form inverts: C's beacon in A's frame is
    ``D = C + d e^{iψ}``; A's beacon in C's frame is ``w = (d − C) e^{−iψ}``.
    """
    pose = np.asarray(pose, dtype=float)
    c = pose[..., 0] + 1j * pose[..., 1]
    rot = np.exp(1j * pose[..., 2])
    beacon_c = c + d_m * rot
    beacon_a = (d_m - c) / rot
    return np.stack(
        [np.abs(beacon_c), np.angle(beacon_c), np.abs(beacon_a), np.angle(beacon_a)], axis=-1
    )


def measurement_jacobian(pose: np.ndarray, d_m: float) -> np.ndarray:
    """(..., 4, 3) analytic Jacobian of :func:`measurements` w.r.t. ``(x, y, ψ)``."""
    pose = np.asarray(pose, dtype=float)
    c = pose[..., 0] + 1j * pose[..., 1]
    rot = np.exp(1j * pose[..., 2])
    beacon_c = c + d_m * rot
    beacon_a = (d_m - c) / rot
    zero = np.zeros_like(c)
    d_beacon_c = np.stack([zero + 1.0, zero + 1j, 1j * d_m * rot], axis=-1)
    d_beacon_a = np.stack([-1.0 / rot, -1j / rot, -1j * beacon_a], axis=-1)
    rows = []
    for z, dz in ((beacon_c, d_beacon_c), (beacon_a, d_beacon_a)):
        ratio = dz / z[..., None]
        rows += [ratio.real * np.abs(z)[..., None], ratio.imag]
    return np.stack(rows, axis=-2)


def _measurement_covariance(range_sigma_m: float, bearing_sigma_rad: float) -> np.ndarray:
    return np.diag([range_sigma_m**2, bearing_sigma_rad**2] * 2)


def cramer_rao_bound(
    pose: np.ndarray, d_m: float, range_sigma_m: float, bearing_sigma_rad: float
) -> np.ndarray:
    """(..., 3, 3) Cramér–Rao bound ``(Hᵀ Σ⁻¹ H)⁻¹`` of C's pose from one mutual observation."""
    H = measurement_jacobian(pose, d_m)
    info = np.swapaxes(H, -1, -2) @ np.linalg.inv(
        _measurement_covariance(range_sigma_m, bearing_sigma_rad)
    )
    return np.asarray(np.linalg.inv(info @ H))


def refine_relative_pose(
    z: np.ndarray,
    d_m: float,
    range_sigma_m: float,
    bearing_sigma_rad: float,
    iterations: int = 4,
) -> tuple[np.ndarray, np.ndarray]:
    """Maximum-likelihood pose (..., 3) and its covariance (..., 3, 3) from measurements (..., 4).

    Gauss–Newton on the whitened residual ``z − h(pose)`` (bearing residuals wrapped), started
    at the closed form; the covariance is ``(Hᵀ Σ⁻¹ H)⁻¹`` at the solution.
    """
    z = np.asarray(z, dtype=float)
    pose = closed_form(z[..., 0], z[..., 1], z[..., 2], z[..., 3], d_m)
    weight = np.array([1 / range_sigma_m, 1 / bearing_sigma_rad] * 2)
    for _ in range(iterations):
        residual = z - measurements(pose, d_m)
        residual[..., 1::2] = wrap_angle(residual[..., 1::2])
        A = measurement_jacobian(pose, d_m) * weight[:, None]
        At = np.swapaxes(A, -1, -2)
        step = np.linalg.solve(At @ A, (At @ (weight * residual)[..., None]))[..., 0]
        pose = pose + step
        pose[..., 2] = wrap_angle(pose[..., 2])
    return pose, cramer_rao_bound(pose, d_m, range_sigma_m, bearing_sigma_rad)


def _linearize_one(
    z: tuple[float, float, float, float], x: float, y: float, psi: float, d_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Residual ``z − h(pose)`` (bearings wrapped) and ``H`` for one event, in plain complex
    arithmetic: the same model as :func:`measurements` and :func:`measurement_jacobian`."""
    c = complex(x, y)
    rot = cmath.exp(1j * psi)
    beacon_c = c + d_m * rot
    beacon_a = (d_m - c) / rot
    H = np.empty((4, 3))
    r = np.empty(4)
    for row, (zz, dz) in enumerate(
        ((beacon_c, (1.0, 1j, 1j * d_m * rot)), (beacon_a, (-1.0 / rot, -1j / rot, -1j * beacon_a)))
    ):
        modulus = abs(zz)
        r[2 * row] = z[2 * row] - modulus
        r[2 * row + 1] = math.remainder(z[2 * row + 1] - cmath.phase(zz), 2 * math.pi)
        for col in range(3):
            ratio = dz[col] / zz
            H[2 * row, col] = ratio.real * modulus
            H[2 * row + 1, col] = ratio.imag
    return r, H


def _refine_one(
    z: tuple[float, float, float, float],
    d_m: float,
    range_sigma_m: float,
    bearing_sigma_rad: float,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`refine_relative_pose` for one event (the fast path the pose graph uses)."""
    x, y, psi = (float(v) for v in closed_form(*z, d_m))
    w = np.array([1 / range_sigma_m, 1 / bearing_sigma_rad] * 2)
    for _ in range(iterations):
        r, H = _linearize_one(z, x, y, psi, d_m)
        A = H * w[:, None]
        step = np.linalg.solve(A.T @ A, A.T @ (w * r))
        x, y, psi = x + step[0], y + step[1], math.remainder(psi + step[2], 2 * math.pi)
        if np.abs(step).max() < 1e-12:
            break
    _, H = _linearize_one(z, x, y, psi, d_m)
    A = H * w[:, None]
    return np.array([x, y, psi]), np.linalg.inv(A.T @ A)


def separations(
    a_m: np.ndarray | float,
    alpha_rad: np.ndarray | float,
    b_m: np.ndarray | float,
    beta_rad: np.ndarray | float,
    d_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Beacon separations ``s1`` (seen by A) and ``s2`` (seen by C), by the cosine rule."""
    s1 = np.abs(_complex(np.asarray(a_m), np.asarray(alpha_rad)) - d_m)
    s2 = np.abs(_complex(np.asarray(b_m), np.asarray(beta_rad)) - d_m)
    return s1, s2


def gap_sigma(
    a_m: np.ndarray | float,
    alpha_rad: np.ndarray | float,
    b_m: np.ndarray | float,
    beta_rad: np.ndarray | float,
    d_m: float,
    range_sigma_m: float,
    bearing_sigma_rad: float,
) -> np.ndarray:
    """Predicted standard deviation of ``s1 − s2`` from the range and bearing noise.

    ``∂s/∂r = Re(conj(w) e^{iφ}) / s`` and ``∂s/∂φ = Re(conj(w) i r e^{iφ}) / s`` for
    ``w = r e^{iφ} − d``, the same for both observations, which are independent.
    """
    variance = np.zeros(np.broadcast_shapes(*(np.shape(x) for x in (a_m, alpha_rad, b_m))))
    for r, phi in ((a_m, alpha_rad), (b_m, beta_rad)):
        unit = np.exp(1j * np.asarray(phi, dtype=float))
        w = np.asarray(r, dtype=float) * unit - d_m
        s = np.abs(w)
        with np.errstate(divide="ignore", invalid="ignore"):
            d_range = (np.conj(w) * unit).real / s
            d_bearing = (np.conj(w) * 1j * np.asarray(r) * unit).real / s
        variance = variance + (d_range * range_sigma_m) ** 2 + (d_bearing * bearing_sigma_rad) ** 2
    return np.asarray(np.sqrt(variance))


def check_observation(
    a_m: float,
    alpha_rad: float,
    b_m: float,
    beta_rad: float,
    d_m: float,
    min_range_m: float = DEFAULT_MIN_RANGE_M,
    min_separation_m: float = DEFAULT_MIN_SEPARATION_M,
) -> None:
    """Raise ``EstimationError`` naming the reason when one event cannot be solved.

    Reasons: a non-finite value; a non-positive beacon offset; a range below ``min_range_m``;
    beacons closer than ``min_separation_m`` (``b·e^{iβ} ≈ d`` or ``a·e^{iα} ≈ d``, where eq. 1–2
    divide by zero).
    """
    values = {"a_m": a_m, "alpha_rad": alpha_rad, "b_m": b_m, "beta_rad": beta_rad, "d_m": d_m}
    for name, value in values.items():
        if not isinstance(value, int | float | np.floating | np.integer) or not math.isfinite(
            value
        ):
            raise EstimationError(
                f"mutual observation: {name} must be a finite number, got {value}"
            )
    if d_m <= 0:
        raise EstimationError(f"mutual observation: beacon offset d_m must be positive, got {d_m}")
    for name, value in (("a_m", a_m), ("b_m", b_m)):
        if value < min_range_m:
            raise EstimationError(
                f"mutual observation: degenerate geometry: range {name} = {value:.4g} m is below "
                f"{min_range_m} m"
            )
    s1, s2 = separations(a_m, alpha_rad, b_m, beta_rad, d_m)
    if s2 < min_separation_m:
        raise EstimationError(
            f"mutual observation: degenerate geometry: b·e^(iβ) ≈ d (beacon separation "
            f"s2 = {float(s2):.4g} m < {min_separation_m} m)"
        )
    if s1 < min_separation_m:
        raise EstimationError(
            f"mutual observation: degenerate geometry: a·e^(iα) ≈ d (beacon separation "
            f"s1 = {float(s1):.4g} m < {min_separation_m} m)"
        )


def relative_pose(
    a_m: float, alpha_rad: float, b_m: float, beta_rad: float, d_m: float
) -> tuple[float, float, float]:
    """Pose ``(x_m, y_m, yaw_rad)`` of C's scanner in A's scanner frame by paper eq. 1–2.

    A sees C's beacon at ``(a_m, alpha_rad)``, C sees A's beacon at ``(b_m, beta_rad)``; each
    beacon is ``d_m`` ahead of its scanner. Raises ``EstimationError`` on NaN or degenerate input.
    """
    check_observation(a_m, alpha_rad, b_m, beta_rad, d_m)
    x, y, yaw = closed_form(a_m, alpha_rad, b_m, beta_rad, d_m)
    return float(x), float(y), float(yaw)


@dataclass(frozen=True)
class MutualFix:
    """One mutual-localization event solved: C's scanner pose in A's scanner frame.

    ``covariance`` is in (x_m, y_m, yaw_rad) of A's frame. ``gap_m = s1 − s2`` and its predicted
    standard deviation ``gap_sigma_m`` make the gate: ``accepted`` when
    ``|gap_m| ≤ gate_sigmas · gap_sigma_m``.
    """

    pose: np.ndarray
    covariance: np.ndarray
    s1_m: float
    s2_m: float
    gap_sigma_m: float
    gate_sigmas: float
    method: Literal["closed_form", "ml"]

    @property
    def gap_m(self) -> float:
        return self.s1_m - self.s2_m

    @property
    def accepted(self) -> bool:
        return abs(self.gap_m) <= self.gate_sigmas * self.gap_sigma_m

    @property
    def gap_sigmas(self) -> float:
        """|s1 − s2| in predicted standard deviations."""
        return abs(self.gap_m) / self.gap_sigma_m


def localize_mutual(
    a_m: float,
    alpha_rad: float,
    b_m: float,
    beta_rad: float,
    d_m: float,
    range_sigma_m: float,
    bearing_sigma_rad: float,
    gate_sigmas: float = 3.0,
    method: Literal["closed_form", "ml"] = "ml",
    min_range_m: float = DEFAULT_MIN_RANGE_M,
    min_separation_m: float = DEFAULT_MIN_SEPARATION_M,
) -> MutualFix:
    """Solve one event: pose, covariance and the s1/s2 gate verdict.

    ``method="closed_form"``: the pose of eq. 1–2 and the covariance ``G Σ Gᵀ`` propagated through
    its analytic Jacobian G. ``method="ml"``: the maximum-likelihood refinement and its
    covariance, the Cramér–Rao bound (the default, and what the pose graph uses).
    """
    check_observation(a_m, alpha_rad, b_m, beta_rad, d_m, min_range_m, min_separation_m)
    if not (range_sigma_m > 0 and bearing_sigma_rad > 0 and gate_sigmas > 0):
        raise EstimationError(
            f"mutual observation: sigmas and gate must be positive, got range_sigma_m="
            f"{range_sigma_m}, bearing_sigma_rad={bearing_sigma_rad}, gate_sigmas={gate_sigmas}"
        )
    if method == "ml":
        pose, covariance = _refine_one(
            (a_m, alpha_rad, b_m, beta_rad), d_m, range_sigma_m, bearing_sigma_rad, 6
        )
    elif method == "closed_form":
        pose = closed_form(a_m, alpha_rad, b_m, beta_rad, d_m)
        G = closed_form_jacobian(a_m, alpha_rad, b_m, beta_rad, d_m)
        covariance = G @ _measurement_covariance(range_sigma_m, bearing_sigma_rad) @ G.T
    else:
        raise EstimationError(f"mutual observation: unknown method {method!r}")
    s1, s2 = separations(a_m, alpha_rad, b_m, beta_rad, d_m)
    sigma = gap_sigma(a_m, alpha_rad, b_m, beta_rad, d_m, range_sigma_m, bearing_sigma_rad)
    return MutualFix(
        pose=pose,
        covariance=0.5 * (covariance + covariance.T),
        s1_m=float(s1),
        s2_m=float(s2),
        gap_sigma_m=float(sigma),
        gate_sigmas=float(gate_sigmas),
        method=method,
    )


#: Gaps needed before the mutual observations' noise follows them, the largest factor, and
#: the gap (in units of that factor) beyond which an observation is rejected.
GAP_SAMPLES = 10
MAX_GAP_SCALE = 3.0
GAP_OUTLIER = 5.0


def gap_scale(gaps: Sequence[float], low: float | None) -> float:
    """The factor on a mutual observation's standard deviations that the s1 − s2 gaps of the
    observations accepted before it call for (``gaps``: |gap| / its predicted deviation).

    The gap is the one redundancy of the four measurements; its predicted deviation comes from
    the configured range and bearing noise. A detection fits one circle to tens of returns, so
    it is much cleaner than one return's noise: the gaps' robust spread (1.4826 × their median)
    says by how much. 1 until ``GAP_SAMPLES`` gaps are in, or with ``low`` None; else within
    [``low``, ``MAX_GAP_SCALE``]."""
    if low is None or len(gaps) < GAP_SAMPLES:
        return 1.0
    return float(np.clip(1.4826 * float(np.median(gaps)), low, MAX_GAP_SCALE))
