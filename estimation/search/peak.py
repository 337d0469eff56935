"""The PDF of a score lattice and its peak: normalisation, dominance, covariance, refinement.

**PDF.** For binary cells (v = ±1), the score (``lattice``) is the log-likelihood of the local
grid given the map and the pose, up to a constant, when each cell agrees with the map with
probability q: log q or log(1 − q) per cell is ½·log(q(1 − q)) + ½·logit(q)·v_L·v_G. The pose
PDF is therefore

    P(T) ∝ exp(β · score(T)),

where β (``beta``) stands for ½·logit(q) divided by the number of cells that one independent
error spans (neighbouring cells are not independent); it is calibrated on simulated searches by
maximising the probability the PDF gives to the true pose (see ``calibrate_beta``). The
``centred`` score (``lattice``) is the small-signal form of the log-likelihood ratio of
"corresponding cells" against "independent cells", 0 in expectation at a wrong pose whatever
the overlap; its β is calibrated the same way.

**Peak.** The best lattice pose is refined by a quadratic fitted to the scores around it
(``refine_peak``), then by maximising the score with the global values interpolated by a cubic
B-spline (``refine_pose``); its dominance (``best_pose_outside``) and covariance
(``peak_covariance``) follow ``PosePdf``'s definitions, computed on the scores.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numba import njit

from estimation.search.correlate import NORMAL_FLOOR, Slices, run_chunked
from estimation.search.lattice import (
    MASK_METRIC,
    Cells,
    Metric,
    check_pair,
    covers_circle,
    known_mask,
    lattice_steps,
    local_cells,
    match_values,
    overlap_weight,
)
from mapping.band import Band

__all__ = [
    "best_pose_outside",
    "normalise",
    "pdf_from_slices",
    "peak_covariance",
    "refine_peak",
    "refine_pose",
]

#: Zero cells around the global values for the spline refinement.
_PAD = 3


# -- the PDF -----------------------------------------------------------------------------------


def pdf_from_slices(
    scores: np.ndarray, slices: Slices, workers: int = 1, in_place: bool = False
) -> np.ndarray:
    """float32 probabilities exp(β·(score − max) − log Z), Z = Σ exp(β·(score − max)), from
    the scores and their per-rotation maxima and sums: one pass writing the result (over the
    scores themselves when ``in_place``). Rotations whose best cell lies more than float32's
    normal range (e^−87) below the peak hold exactly 0; in the others, cells are floored at
    e^−87 — float32's exp is ten times slower where it returns subnormal numbers."""
    assert slices.beta is not None
    beta = slices.beta
    top = float(slices.maxima.max())
    relative = beta * (slices.maxima - top)
    live = np.flatnonzero(relative > -NORMAL_FLOOR)
    log_total = math.log(float((np.exp(relative[live]) * slices.sums[live]).sum()))
    if in_place:
        prob = scores
        prob[np.flatnonzero(relative <= -NORMAL_FLOOR)] = 0.0
    else:
        prob = np.zeros(scores.shape, dtype=np.float32)
    b = np.float32(beta)
    # The maxima are float32 scores, so ``peak`` is exact and s − peak loses nothing near the
    # peak; log Z is subtracted after scaling, where its rounding is relative to log Z alone.
    peak, log_z = np.float32(top), np.float32(log_total)
    sums = np.zeros(len(scores))

    def exponentiate(ts: np.ndarray) -> None:
        for t in ts:
            target = prob[t]
            np.subtract(scores[t], peak, out=target)
            target *= b
            target -= log_z
            np.maximum(target, np.float32(-NORMAL_FLOOR), out=target)
            np.exp(target, out=target)
            sums[t] = target.sum(dtype=np.float64)

    run_chunked(exponentiate, live, workers)
    total = float(sums.sum())
    if abs(total - 1.0) > 1e-7:  # float32 rounding of the exponents: put the sum back on 1
        factor = np.float32(1.0 / total)

        def rescale(ts: np.ndarray) -> None:
            for t in ts:
                prob[t] *= factor

        run_chunked(rescale, live, workers)
    return prob


def normalise(scores: np.ndarray, beta: float) -> np.ndarray:
    """float32 probabilities ∝ exp(β·(score − max)), summing to 1."""
    scores = np.asarray(scores, dtype=np.float32)
    slices = Slices(beta, np.empty(len(scores)), np.zeros(len(scores)))
    scratch = np.empty(scores.shape[1:], dtype=np.float32)
    for t in range(len(scores)):
        slices.record(t, scores[t], scratch)
    return pdf_from_slices(scores, slices)


# -- the peak: refinement, dominance, covariance -----------------------------------------------


def _reach(radius: float, step: float) -> int:
    return int(radius / step + 1e-9) if step > 0 else 0


def _neighbourhood(
    index: tuple[int, int, int],
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    radius_m: float,
    radius_rad: float,
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray, np.ndarray]:
    """The peak's neighbourhood as ``PosePdf`` defines it: the cells within ``radius_m`` (x, y)
    and ``radius_rad`` (yaw, wrapped) of the cell ``index``. Returns the index box (t, y, x
    arrays), the (t, y, x) mask of the cells inside it, and their offsets (n, 3)."""
    bt, by, bx = index
    sx, sy, syaw = lattice_steps(x_m, y_m, yaw_rad)
    axes = []
    for n, i, step, radius, wraps in (
        (len(yaw_rad), bt, syaw, radius_rad, covers_circle(yaw_rad)),
        (len(y_m), by, sy, radius_m, False),
        (len(x_m), bx, sx, radius_m, False),
    ):
        reach = _reach(radius, step)
        if wraps:
            reach = min(reach, (n - 1) // 2)
            axes.append(np.arange(i - reach, i + reach + 1) % n)
        else:
            axes.append(np.arange(max(0, i - reach), min(n, i + reach + 1)))
    it, iy, ix = axes
    yaw, y, x = np.meshgrid(yaw_rad[it], y_m[iy], x_m[ix], indexing="ij")
    dyaw = (yaw - yaw_rad[bt] + math.pi) % (2.0 * math.pi) - math.pi
    dx, dy = x - x_m[bx], y - y_m[by]
    inside = (np.hypot(dx, dy) <= radius_m + 1e-12) & (np.abs(dyaw) <= radius_rad + 1e-12)
    offsets = np.stack([dx[inside], dy[inside], dyaw[inside]], axis=-1)
    return (it, iy, ix), inside, offsets


def best_pose_outside(
    scores: np.ndarray,
    index: tuple[int, int, int],
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    radius_m: float,
    radius_rad: float,
    *,
    maxima: np.ndarray | None = None,
) -> float:
    """The best score outside the peak's neighbourhood (−inf if every cell is inside it).

    ``maxima``: the maximum of each rotation's slice, if already known.
    """
    (it, iy, ix), inside, _ = _neighbourhood(index, x_m, y_m, yaw_rad, radius_m, radius_rad)
    if maxima is None:
        maxima = scores.reshape(len(scores), -1).max(axis=1)
    per_slice = np.array(maxima, dtype=np.float64)
    for row, t in enumerate(it):
        sub = scores[t].astype(np.float64)  # one slice: cheap
        box = sub[np.ix_(iy, ix)]
        box[inside[row]] = -np.inf
        sub[np.ix_(iy, ix)] = box
        per_slice[t] = sub.max()
    return float(per_slice.max())


def peak_covariance(
    scores: np.ndarray,
    index: tuple[int, int, int],
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    beta: float,
    radius_m: float,
    radius_rad: float,
) -> np.ndarray:
    """3×3 covariance (m, m, rad) of the PDF ∝ exp(β·score) over the peak's neighbourhood, as
    ``PosePdf.covariance`` computes it: second moments about the neighbourhood's mean, plus the
    variance of a uniform cell (step²/12) along each axis."""
    (it, iy, ix), inside, offsets = _neighbourhood(index, x_m, y_m, yaw_rad, radius_m, radius_rad)
    box = scores[np.ix_(it, iy, ix)].astype(np.float64)[inside]
    w = np.exp(beta * (box - box.max()))
    w /= w.sum()
    centred = offsets - (w[:, None] * offsets).sum(axis=0)
    cov = (w[:, None, None] * centred[:, :, None] * centred[:, None, :]).sum(axis=0)
    cov += np.diag(np.square(lattice_steps(x_m, y_m, yaw_rad))) / 12.0
    return np.asarray(0.5 * (cov + cov.T))


def refine_peak(scores: np.ndarray, index: tuple[int, int, int], yaw_wraps: bool) -> np.ndarray:
    """Sub-cell offset (x, y, yaw, in lattice steps) of the score's maximum near ``index``.

    A quadratic (cross terms included) is fitted by least squares to the 3×3×3 neighbourhood and
    its vertex taken when it is a maximum; else each axis gets its own parabola through three
    samples. Axes without a neighbour on both sides stay at 0; offsets are clipped to ±1 step.
    """
    shape = scores.shape  # (T, Y, X)
    t0, y0, x0 = index
    usable = []  # (pose axis, array axis)
    for k, axis in ((0, 2), (1, 1), (2, 0)):
        i, n = index[axis], shape[axis]
        if (axis == 0 and yaw_wraps and n >= 3) or 0 < i < n - 1:
            usable.append((k, axis))
    step = np.zeros(3)
    if not usable:
        return step
    grid = np.array(np.meshgrid(*[[-1, 0, 1]] * len(usable), indexing="ij")).reshape(
        len(usable), -1
    )
    values = []
    for column in grid.T:
        cell = [t0, y0, x0]
        for (_, axis), d in zip(usable, column, strict=True):
            cell[axis] = (cell[axis] + int(d)) % shape[axis]
        values.append(float(scores[cell[0], cell[1], cell[2]]))
    f = np.array(values)
    m = len(usable)
    pairs = [(i, j) for i in range(m) for j in range(i, m)]
    design = np.column_stack(
        [np.ones(grid.shape[1]), *grid, *[grid[i] * grid[j] for i, j in pairs]]
    )
    coef = np.linalg.lstsq(design, f, rcond=None)[0]
    g = coef[1 : 1 + m]
    H = np.zeros((m, m))
    for (i, j), c in zip(pairs, coef[1 + m :], strict=True):
        H[i, j] += c if i != j else 2 * c
        if i != j:
            H[j, i] += c
    if np.linalg.eigvalsh(H).max() < 0:
        delta = -np.linalg.solve(H, g)
    else:
        delta = np.zeros(m)
        centre = grid.shape[1] // 2
        for r in range(m):
            others = np.all(np.delete(grid, r, axis=0) == 0, axis=0)
            fm = f[others & (grid[r] == -1)][0]
            fp = f[others & (grid[r] == 1)][0]
            curvature = fm - 2 * f[centre] + fp
            if curvature < 0:
                delta[r] = (fm - fp) / (2 * curvature)
    for (k, _), d in zip(usable, delta, strict=True):
        step[k] = float(np.clip(d, -1.0, 1.0))
    return step


@njit(cache=True, nogil=True, inline="always")
def _bspline(t: float) -> tuple[float, float, float, float, float, float, float, float]:
    """The cubic B-spline's four weights at fraction t of a cell, and their derivatives."""
    u = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    return (
        u * u * u / 6.0,
        (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
        (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
        t3 / 6.0,
        -u * u / 2.0,
        (3.0 * t2 - 4.0 * t) / 2.0,
        (-3.0 * t2 + 2.0 * t + 1.0) / 2.0,
        t2 / 2.0,
    )


@njit(cache=True, nogil=True, fastmath=True)
def _spline_score(
    centres: np.ndarray,
    w: np.ndarray,
    coefficients: np.ndarray,
    origin: np.ndarray,
    resolution_m: float,
    pose: np.ndarray,
    gradient: np.ndarray,
) -> float:
    """Σ w_k · v_G(T·c_k) with v_G interpolated by a cubic B-spline through the global cell
    centres (``coefficients``: the prefiltered values, padded by ``_PAD`` cells): the score as a
    smooth function of the pose; its gradient (x, y, yaw) is written into ``gradient``.

    Two passes: where each centre falls (vectorised), then the 4 × 4 coefficients around it."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rows, cols = coefficients.shape
    scale = 1.0 / resolution_m
    shift_x = (pose[0] - origin[0]) * scale - 0.5 + _PAD
    shift_y = (pose[1] - origin[1]) * scale - 0.5 + _PAD
    count = len(w)
    frac_x = np.empty(count)
    frac_y = np.empty(count)
    first = np.empty(count, dtype=np.int64)  # flat index of the 4 × 4 coefficients; -1: none
    for k in range(count):
        fx = (c * centres[k, 0] - s * centres[k, 1]) * scale + shift_x
        fy = (s * centres[k, 0] + c * centres[k, 1]) * scale + shift_y
        j0 = np.floor(fx)
        i0 = np.floor(fy)
        frac_x[k] = fx - j0
        frac_y[k] = fy - i0
        inside = (i0 >= 1) & (j0 >= 1) & (i0 + 2 < rows) & (j0 + 2 < cols)  # else the values are 0
        first[k] = np.int64(i0 - 1) * cols + np.int64(j0 - 1) if inside else -1
    flat = coefficients.ravel()
    total = 0.0
    gx = 0.0
    gy = 0.0
    gt = 0.0
    for k in range(count):
        i = first[k]
        if i < 0:
            continue
        bx0, bx1, bx2, bx3, dx0, dx1, dx2, dx3 = _bspline(frac_x[k])
        by0, by1, by2, by3, dy0, dy1, dy2, dy3 = _bspline(frac_y[k])
        value = 0.0
        dfx = 0.0
        dfy = 0.0
        for weight, slope in ((by0, dy0), (by1, dy1), (by2, dy2), (by3, dy3)):
            c0, c1, c2, c3 = flat[i], flat[i + 1], flat[i + 2], flat[i + 3]
            row_value = bx0 * c0 + bx1 * c1 + bx2 * c2 + bx3 * c3
            value += weight * row_value
            dfx += weight * (dx0 * c0 + dx1 * c1 + dx2 * c2 + dx3 * c3)
            dfy += slope * row_value
            i += cols
        rx = c * centres[k, 0] - s * centres[k, 1]
        ry = s * centres[k, 0] + c * centres[k, 1]
        total += w[k] * value
        gx += w[k] * dfx
        gy += w[k] * dfy
        gt += w[k] * (dfx * -ry + dfy * rx)
    gradient[0] = gx * scale
    gradient[1] = gy * scale
    gradient[2] = gt * scale
    return total


def refine_pose(
    local: Band,
    global_: Band,
    start: np.ndarray,
    metric: Metric,
    bounds: np.ndarray,
) -> np.ndarray:
    """Maximise the score with the global values interpolated by a cubic B-spline, from
    ``start`` (x, y, yaw) within ``bounds`` (3, 2): a continuous refinement of the lattice's best
    pose, which the lattice samples only every cell and every angular step. (A bilinear
    interpolant has kinks exactly where the lattice puts the local cell centres.)"""
    from scipy.ndimage import spline_filter

    r = check_pair(local, global_)
    # (cells, interpolated global values) of each term: the score, and for the ``excess`` score
    # the overlap count weighted by −c (``lattice``).
    terms = [(local_cells(local, metric), match_values(global_, metric))]
    weight = overlap_weight(local, global_, metric, None)
    if weight != 0.0:
        mask = local_cells(known_mask(local), MASK_METRIC)
        terms.append(
            (Cells(mask.u, -weight * mask.w), match_values(known_mask(global_), MASK_METRIC))
        )
    splines = [
        (cells.u * r, cells.w, spline_filter(np.pad(values, _PAD), order=3, mode="mirror"))
        for cells, values in terms
    ]
    origin = np.asarray(global_.lower_xy, dtype=float)
    # Scale the variables so that the bounds are ±1 along each.
    scale = np.maximum(bounds[:, 1] - bounds[:, 0], 1e-12) / 2.0
    centre = bounds.mean(axis=1)
    gradient = np.zeros(3)
    part = np.zeros(3)

    def cost(z: np.ndarray) -> tuple[float, np.ndarray]:
        pose = centre + z * scale
        value = 0.0
        gradient.fill(0.0)
        for centres, w, coefficients in splines:
            value += _spline_score(centres, w, coefficients, origin, r, pose, part)
            np.add(gradient, part, out=gradient)
        return -value, -gradient * scale

    start = np.clip(np.asarray(start, dtype=float), bounds[:, 0], bounds[:, 1])
    best = _minimise_in_box(cost, (start - centre) / scale)
    return np.asarray(centre + best * scale, dtype=float)


def _minimise_in_box(
    cost: Callable[[np.ndarray], tuple[float, np.ndarray]],
    z: np.ndarray,
    iterations: int = 40,
) -> np.ndarray:
    """Minimise a smooth cost (value, gradient) within the box [−1, 1]ⁿ: quasi-Newton (BFGS)
    steps, projected onto the box, with backtracking. A few variables: a dozen evaluations,
    where scipy's L-BFGS-B spends most of its time in its own bookkeeping."""
    f, g = cost(z)
    inverse = np.eye(len(z)) * (0.1 / max(float(np.abs(g).max()), 1e-12))
    for _ in range(iterations):
        direction = -inverse @ g
        step = 1.0
        while True:
            trial = np.clip(z + step * direction, -1.0, 1.0)
            moved = trial - z
            f_trial, g_trial = cost(trial)
            if f_trial <= f + 1e-4 * float(g @ moved) or step < 1e-4:
                break
            step *= 0.5
        if f_trial > f or np.abs(moved).max() < 1e-7:
            break
        change = g_trial - g
        curvature = float(moved @ change)
        if curvature > 1e-12:
            rho = 1.0 / curvature
            identity = np.eye(len(z))
            inverse = (identity - rho * np.outer(moved, change)) @ inverse @ (
                identity - rho * np.outer(change, moved)
            ) + rho * np.outer(moved, moved)
        z, f, g = trial, f_trial, g_trial
        if abs(float(g @ moved)) < 1e-10 * max(1.0, abs(f)):
            break
    return z
