"""A pose probability density on an (x, y, yaw) lattice: what a global-localization search yields.

The exhaustive search (docs/design.md §7) scores every pose of a window and keeps the whole PDF; the
pose graph consumes it twice (docs/design.md §5): its best pose **seeds** a new station when the
peak is dominant, and its high-probability region **validates** the optimized pose. This module
holds only the data type and those questions; the search itself lives elsewhere.

Lattices are uniform and increasing: ``x_m`` (X,), ``y_m`` (Y,), ``yaw_rad`` (T,); ``prob`` is
(T, Y, X), non-negative, summing to 1. A yaw lattice whose T steps span 2π wraps around.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Self

import numpy as np

from estimation.errors import EstimationError
from sensors.geometry.se2 import wrap_angle

__all__ = ["PosePdf"]


@dataclass(frozen=True)
class _Peak:
    weights: np.ndarray  # probabilities of the neighbourhood's cells
    offsets: np.ndarray  # (n, 3) their offsets from the best cell (yaw wrapped)
    elsewhere: float  # the largest probability outside the neighbourhood


_TWO_PI = 2.0 * math.pi
#: What a pickled ``PosePdf`` holds.
_STATE = ("x_m", "y_m", "yaw_rad", "_raw", "_total", "_steps")


def _lattice(name: str, values: np.ndarray) -> tuple[np.ndarray, float]:
    values = np.array(values, dtype=float)
    if values.ndim != 1 or len(values) == 0:
        raise EstimationError(f"PosePdf: {name} must be a non-empty 1-D lattice")
    if not np.isfinite(values).all():
        raise EstimationError(f"PosePdf: {name} holds NaN or inf")
    if len(values) == 1:
        return values, 0.0
    steps = np.diff(values)
    step = float(steps.mean())
    if step <= 0 or np.abs(steps - step).max() > 1e-6 * max(1.0, abs(step)):
        raise EstimationError(f"PosePdf: {name} must be uniform and increasing")
    return values, step


class PosePdf:
    """Normalised probabilities ``prob[t, y, x]`` of the pose ``(x_m[x], y_m[y], yaw_rad[t])``.

    The pose is that of some frame (a station's robot frame) in a reference frame (the map, or an
    earlier station): whatever the search was asked for. Arrays are copied and made read-only;
    the object is immutable and equal only to itself.

    A search's float32 probabilities are kept as float32, with their float64 sum: ``prob`` and
    every answer are those of the float64 array ``prob / sum`` — the same numbers, bit for bit,
    as normalising a float64 copy — at half its memory (a loop closure's window holds up to
    1.6 M poses: 6 MB a PDF instead of 12.5, for as long as the graph keeps it). Float64 input
    is normalised and kept as float64.
    """

    __slots__ = ("_cache", "_raw", "_steps", "_total", "x_m", "y_m", "yaw_rad")

    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    _raw: np.ndarray  # the probabilities as given (float32), or normalised (float64)
    _total: np.float64  # their sum (1 for float64)
    _steps: tuple[float, float, float]
    _cache: dict[object, Any]

    def __init__(
        self, x_m: np.ndarray, y_m: np.ndarray, yaw_rad: np.ndarray, prob: np.ndarray
    ) -> None:
        lattices = {}
        for name, given in (("x_m", x_m), ("y_m", y_m), ("yaw_rad", yaw_rad)):
            values, step = _lattice(name, given)
            values.setflags(write=False)
            object.__setattr__(self, name, values)
            lattices[name] = step
        single = np.asarray(prob).dtype == np.float32
        raw = np.array(prob, dtype=np.float32 if single else float)
        shape = (len(self.yaw_rad), len(self.y_m), len(self.x_m))
        if raw.shape != shape:
            raise EstimationError(
                f"PosePdf: prob must have shape (T, Y, X) = {shape}, got {raw.shape}"
            )
        if not np.isfinite(raw).all() or raw.min() < 0:
            raise EstimationError("PosePdf: prob must be finite and non-negative")
        # The sum of the float64 values (the same pairwise sum a float64 copy would give).
        total = (raw.astype(float) if single else raw).sum()
        # A PDF summed in float32 over millions of cells is off by ~1e-6; renormalise such
        # rounding, reject anything larger.
        if abs(total - 1.0) > 1e-4:
            raise EstimationError(f"PosePdf: prob must sum to 1, sums to {total:.9g}")
        if not single:
            raw /= total
            total = np.float64(1.0)
        if lattices["yaw_rad"] * len(self.yaw_rad) > _TWO_PI + 1e-9:
            raise EstimationError("PosePdf: yaw_rad lattice covers more than 2π")
        raw.setflags(write=False)
        object.__setattr__(self, "_raw", raw)
        object.__setattr__(self, "_total", total)
        object.__setattr__(self, "_steps", (lattices["x_m"], lattices["y_m"], lattices["yaw_rad"]))
        object.__setattr__(self, "_cache", {})

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"PosePdf is immutable: cannot set {name!r}")

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"PosePdf is immutable: cannot delete {name!r}")

    def __getstate__(self) -> dict[str, object]:
        # Pickled between a mission's processes; the cache is made again.
        return {name: getattr(self, name) for name in _STATE}

    def __setstate__(self, state: dict[str, Any]) -> None:
        for name in _STATE:
            value = state[name]
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "_cache", {})

    def __repr__(self) -> str:
        return f"PosePdf({len(self.yaw_rad)} × {len(self.y_m)} × {len(self.x_m)} poses)"

    @property
    def prob(self) -> np.ndarray:
        """(T, Y, X) float64 probabilities summing to 1 (made on each call, read-only)."""
        prob = self._raw.astype(float)
        prob /= self._total
        prob.setflags(write=False)
        return prob

    @property
    def nbytes(self) -> int:
        """The memory the probabilities take."""
        return int(self._raw.nbytes)

    def _value(self, index: tuple[int, ...]) -> float:
        """The probability of one cell (``prob[index]``, without making ``prob``)."""
        return float(self._raw[index] / self._total)

    # -- construction -----------------------------------------------------------------------

    @classmethod
    def from_scores(
        cls, x_m: np.ndarray, y_m: np.ndarray, yaw_rad: np.ndarray, scores: np.ndarray
    ) -> Self:
        """Normalise non-negative scores (T, Y, X) into a PDF."""
        scores = np.asarray(scores, dtype=float)
        if not np.isfinite(scores).all() or scores.min() < 0 or scores.sum() <= 0:
            raise EstimationError("PosePdf: scores must be finite, non-negative, not all zero")
        return cls(x_m, y_m, yaw_rad, scores / scores.sum())

    @classmethod
    def from_gaussian(
        cls,
        mean: np.ndarray,
        covariance: np.ndarray,
        x_m: np.ndarray,
        y_m: np.ndarray,
        yaw_rad: np.ndarray,
    ) -> Self:
        """A Gaussian (x, y, yaw) sampled on the lattice (yaw differences wrapped)."""
        mean = np.asarray(mean, dtype=float)
        info = np.linalg.inv(np.asarray(covariance, dtype=float))
        yaw, y, x = np.meshgrid(yaw_rad, y_m, x_m, indexing="ij")
        delta = np.stack([x - mean[0], y - mean[1], wrap_angle(yaw - mean[2])], axis=-1)
        exponent = -0.5 * np.einsum("...i,ij,...j->...", delta, info, delta)
        return cls.from_scores(x_m, y_m, yaw_rad, np.exp(exponent - exponent.max()))

    # -- lattice geometry -------------------------------------------------------------------

    @property
    def steps(self) -> tuple[float, float, float]:
        """Lattice steps (x_m, y_m, yaw_rad); 0 along an axis of one sample."""
        return self._steps

    @property
    def yaw_wraps(self) -> bool:
        """Whether the yaw lattice spans the whole circle."""
        step = self.steps[2]
        return step > 0 and abs(step * len(self.yaw_rad) - _TWO_PI) < 1e-6

    def pose_at(self, index: tuple[int, int, int]) -> np.ndarray:
        """The lattice pose (x, y, yaw) of ``prob[t, y, x]``."""
        t, y, x = index
        return np.array([self.x_m[x], self.y_m[y], self.yaw_rad[t]])

    def nearest_index(self, pose: np.ndarray) -> tuple[int, int, int] | None:
        """``(t, y, x)`` of the lattice cell holding ``pose``, or None outside the lattice."""
        x, y, yaw = (float(v) for v in np.asarray(pose, dtype=float))
        out = []
        for value, lattice, step in (
            (x, self.x_m, self.steps[0]),
            (y, self.y_m, self.steps[1]),
        ):
            i = round((value - lattice[0]) / step) if step > 0 else 0
            if not 0 <= i < len(lattice) or abs(value - lattice[i]) > max(step, 1e-9) / 2 + 1e-12:
                return None
            out.append(i)
        step = self.steps[2]
        offset = float(wrap_angle(yaw - self.yaw_rad[0]))
        if self.yaw_wraps:
            t = round((offset % _TWO_PI) / step) % len(self.yaw_rad)
        else:
            span = step * (len(self.yaw_rad) - 1)
            if offset < -max(step, 1e-9) / 2:
                offset += _TWO_PI  # the window may start anywhere on the circle
            t = round(offset / step) if step > 0 else 0
            if not 0 <= t < len(self.yaw_rad) or offset > span + max(step, 1e-9) / 2 + 1e-12:
                return None
        return int(t), out[1], out[0]

    # -- the peak ---------------------------------------------------------------------------

    def best_index(self) -> tuple[int, int, int]:
        """``(t, y, x)`` of the most probable cell."""
        # float32 values keep their order when divided by the sum in float64 (their quotients
        # are at least 2^-24 apart, float64 rounds at 2^-53): the same cell as prob's argmax.
        t, y, x = np.unravel_index(int(np.argmax(self._raw)), self._raw.shape)
        return int(t), int(y), int(x)

    def best_pose(self, refine: bool = True) -> np.ndarray:
        """The most probable pose. With ``refine``, one Newton step on the log-probability (a
        quadratic through the peak's 3×3×3 neighbourhood, cross terms included) places it between
        lattice points — exact for a Gaussian peak; the step is clipped to one cell."""
        cache = self._cache
        cached = cache.get(("best", refine))
        if cached is None:
            cached = cache[("best", refine)] = self._best_pose(refine)
        return cached.copy()

    def _best_pose(self, refine: bool) -> np.ndarray:
        index = self.best_index()
        pose = self.pose_at(index)
        if not refine:
            return pose
        # Axes in pose order (x, y, yaw) and their array axes in prob (t, y, x).
        usable = []
        for k, (axis, step) in enumerate(
            ((2, self.steps[0]), (1, self.steps[1]), (0, self.steps[2]))
        ):
            n, i = self._raw.shape[axis], index[axis]
            if step > 0 and ((axis == 0 and self.yaw_wraps) or 0 < i < n - 1):
                usable.append((k, axis, step))
        if not usable:
            return pose

        def log_p(offsets: dict[int, int]) -> float:
            cell = list(index)
            for axis, o in offsets.items():
                cell[axis] = (cell[axis] + o) % self._raw.shape[axis]
            value = self._value(tuple(cell))
            return math.log(value) if value > 0 else -math.inf

        m = len(usable)
        grad, hess = np.zeros(m), np.zeros((m, m))
        f0 = log_p({})
        for r, (_, ar, hr) in enumerate(usable):
            fp, fm = log_p({ar: 1}), log_p({ar: -1})
            grad[r] = (fp - fm) / (2 * hr)
            hess[r, r] = (fp - 2 * f0 + fm) / hr**2
            for c in range(r):
                _, ac, hc = usable[c]
                cross = (
                    log_p({ar: 1, ac: 1})
                    - log_p({ar: 1, ac: -1})
                    - log_p({ar: -1, ac: 1})
                    + log_p({ar: -1, ac: -1})
                )
                hess[r, c] = hess[c, r] = cross / (4 * hr * hc)
        if not (np.isfinite(grad).all() and np.isfinite(hess).all()):
            return pose
        if np.linalg.eigvalsh(hess).max() >= 0:
            return pose
        newton = -np.linalg.solve(hess, grad)
        for r, (k, _, h) in enumerate(usable):
            pose[k] += float(np.clip(newton[r], -h, h))
        pose[2] = float(wrap_angle(pose[2]))
        return pose

    def _peak(self, peak_radius_m: float, peak_radius_rad: float) -> _Peak:
        """The peak's neighbourhood (cells within the radii of the best cell), computed on the
        sub-box around the best cell only, and cached: PDFs of a full search are large."""
        cache = self._cache
        cached = cache.get((peak_radius_m, peak_radius_rad))
        if cached is not None:
            return cached
        bt, by, bx = self.best_index()
        axes = []
        for n, i, step, radius, wraps in (
            (len(self.yaw_rad), bt, self.steps[2], peak_radius_rad, self.yaw_wraps),
            (len(self.y_m), by, self.steps[1], peak_radius_m, False),
            (len(self.x_m), bx, self.steps[0], peak_radius_m, False),
        ):
            reach = int(radius / step + 1e-9) if step > 0 else 0
            if wraps:
                reach = min(reach, (n - 1) // 2)
                axes.append(np.arange(i - reach, i + reach + 1) % n)
            else:
                axes.append(np.arange(max(0, i - reach), min(n, i + reach + 1)))
        it, iy, ix = axes
        box = np.ix_(it, iy, ix)
        best = self.pose_at((bt, by, bx))
        yaw, y, x = np.meshgrid(self.yaw_rad[it], self.y_m[iy], self.x_m[ix], indexing="ij")
        delta = np.stack([x - best[0], y - best[1], wrap_angle(yaw - best[2])], axis=-1)
        inside = (np.hypot(delta[..., 0], delta[..., 1]) <= peak_radius_m + 1e-12) & (
            np.abs(delta[..., 2]) <= peak_radius_rad + 1e-12
        )
        rest = self._raw.copy()
        rest[box] = np.where(inside, 0.0, self._raw[box])
        peak = _Peak(
            weights=self._raw[box][inside].astype(float) / self._total,
            offsets=delta[inside],
            elsewhere=float(rest.max() / self._total),
        )
        cache[(peak_radius_m, peak_radius_rad)] = peak
        return peak

    def peak_ratio(self, peak_radius_m: float = 0.5, peak_radius_rad: float = 0.1745) -> float:
        """Best probability over the best one outside the peak's neighbourhood (inf if none).

        The neighbourhood: within ``peak_radius_m`` and ``peak_radius_rad`` of the best cell.
        """
        elsewhere = self._peak(peak_radius_m, peak_radius_rad).elsewhere
        return math.inf if elsewhere <= 0 else float(self._raw.max() / self._total) / elsewhere

    def is_dominant(
        self, dominance_ratio: float, peak_radius_m: float = 0.5, peak_radius_rad: float = 0.1745
    ) -> bool:
        """Whether the peak stands out by at least ``dominance_ratio`` (seed condition)."""
        return self.peak_ratio(peak_radius_m, peak_radius_rad) >= dominance_ratio

    def covariance(self, peak_radius_m: float = 0.5, peak_radius_rad: float = 0.1745) -> np.ndarray:
        """3×3 covariance (m, m, rad) of the probability in the peak's neighbourhood.

        Second moments about the probability-weighted mean of the neighbourhood (yaw wrapped),
        plus the variance of a uniform cell (step²/12) along each axis.
        """
        peak = self._peak(peak_radius_m, peak_radius_rad)
        w = peak.weights / peak.weights.sum()
        d = peak.offsets
        centred = d - (w[:, None] * d).sum(axis=0)
        cov = centred.T @ (w[:, None] * centred)
        cov += np.diag(np.square(self.steps)) / 12.0
        return np.asarray(0.5 * (cov + cov.T))

    # -- the high-probability region --------------------------------------------------------

    def density_threshold(self, mass: float) -> float:
        """The smallest cell probability of the highest-probability region holding ``mass``."""
        if not 0 < mass < 1:
            raise EstimationError(f"PosePdf: mass must be in (0, 1), got {mass}")
        ordered = np.sort(self.prob, axis=None)[::-1]
        k = int(np.searchsorted(np.cumsum(ordered), mass - 1e-12))
        return float(ordered[min(k, len(ordered) - 1)])

    def region(self, mass: float) -> np.ndarray:
        """Boolean (T, Y, X) mask of the highest-probability region holding ``mass``."""
        return np.asarray(self.prob >= self.density_threshold(mass))

    def contains(self, pose: np.ndarray, mass: float) -> bool:
        """Whether ``pose`` falls in a cell of the region holding ``mass`` of the probability.

        Poses outside the lattice are outside the region.
        """
        index = self.nearest_index(pose)
        return index is not None and self._value(index) >= self.density_threshold(mass)

    def mass_above(self, pose: np.ndarray) -> float:
        """Probability of the cells more probable than ``pose``'s cell (1 outside the lattice):
        a pose is in the region holding ``mass`` when this is below ``mass``."""
        index = self.nearest_index(pose)
        if index is None:
            return 1.0
        prob = self.prob
        return float(prob[prob > prob[index]].sum())
