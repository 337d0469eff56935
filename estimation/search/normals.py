"""The normal of the plane through a point's neighbours: the smallest principal axis of their
scatter, by cyclic Jacobi rotations on 3×3 matrices (compiled kernels; the registration's
normals, docs/design.md §7)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["jacobi3", "plane_normals"]


@njit(cache=True, nogil=True)
def plane_normals(points: np.ndarray, index: np.ndarray, least: int, out: np.ndarray) -> None:
    """Into ``out[i]``: the unit normal of the plane through point i's neighbours ``index[i]``
    (a :class:`PointGrid` answer: ``len(points)`` where none), the axis of their scatter
    matrix with the smallest eigenvalue; left as is where fewer than ``least`` neighbours were
    found."""
    n, k = index.shape
    scatter = np.empty((3, 3))
    vectors = np.empty((3, 3))
    mean = np.empty(3)
    for i in range(n):
        count = 0
        mean[:] = 0.0
        for j in range(k):
            m = index[i, j]
            if m < n:
                count += 1
                for a in range(3):
                    mean[a] += points[m, a]
        if count < least:
            continue
        mean /= count
        scatter[:] = 0.0
        for j in range(k):
            m = index[i, j]
            if m < n:
                for a in range(3):
                    da = points[m, a] - mean[a]
                    for b in range(a, 3):
                        scatter[a, b] += da * (points[m, b] - mean[b])
        scatter[1, 0], scatter[2, 0], scatter[2, 1] = scatter[0, 1], scatter[0, 2], scatter[1, 2]
        smallest = jacobi3(scatter, vectors)
        for a in range(3):
            out[i, a] = vectors[a, smallest]


@njit(cache=True, nogil=True)
def jacobi3(a: np.ndarray, v: np.ndarray) -> int:
    """Diagonalises the symmetric 3×3 ``a`` in place by cyclic Jacobi rotations; ``v`` receives
    the eigenvectors as columns. Returns the column of the smallest eigenvalue."""
    v[:] = 0.0
    for d in range(3):
        v[d, d] = 1.0
    for _ in range(30):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        size = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off == 0.0 or off <= 1e-30 * size:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            if a[p, q] == 0.0:
                continue
            theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
            t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
            c = 1.0 / math.sqrt(t * t + 1.0)
            s = t * c
            for r in range(3):  # a J
                arp, arq = a[r, p], a[r, q]
                a[r, p], a[r, q] = c * arp - s * arq, s * arp + c * arq
            for r in range(3):  # Jᵀ (a J)
                apr, aqr = a[p, r], a[q, r]
                a[p, r], a[q, r] = c * apr - s * aqr, s * apr + c * aqr
            for r in range(3):  # the eigenvectors: v J
                vrp, vrq = v[r, p], v[r, q]
                v[r, p], v[r, q] = c * vrp - s * vrq, s * vrp + c * vrq
    smallest = 0
    for d in range(1, 3):
        if a[d, d] < a[smallest, smallest]:
            smallest = d
    return smallest
