"""Ground-truth occupancy of a simulated world, for map-quality metrics.

A voxel is occupied when a surface of the world passes through it. Voxels are half-open cubes
``[origin + i·res, origin + (i + 1)·res)`` per axis; a surface lying exactly on a voxel boundary
belongs to the voxel above the boundary (the same convention a point on the boundary gets).
Surfaces are sampled on a barycentric lattice no coarser than a quarter voxel, so a surface that
only clips a voxel's corner by less than that may be missed. Only surfaces are occupied: the
inside of a pillar is as unobservable to a laser as it is to this definition.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sensors.errors import SensorError
from sensors.sim.scene import WorldMesh

__all__ = ["BandImage", "VoxelSet", "band_share", "surface_voxels"]

#: Points within this fraction of a voxel below a boundary count as on it (float round-off).
_BOUNDARY_EPS = 1e-6


@dataclass(frozen=True)
class VoxelSet:
    """A set of voxels of edge ``resolution_m`` on the lattice anchored at ``origin_m``."""

    resolution_m: float
    origin_m: np.ndarray  # (3,) corner of voxel (0, 0, 0), map frame
    indices: np.ndarray  # (N, 3) int64, unique, lexicographically sorted

    def __len__(self) -> int:
        return len(self.indices)

    def centers(self) -> np.ndarray:
        """(N, 3) voxel centres in the map frame."""
        return np.asarray(self.origin_m + (self.indices + 0.5) * self.resolution_m)

    def band(self, z_min_m: float, z_max_m: float) -> VoxelSet:
        """The voxels whose centres lie at heights within [z_min_m, z_max_m)."""
        z = self.centers()[:, 2]
        keep = (z >= z_min_m) & (z < z_max_m)
        return VoxelSet(self.resolution_m, self.origin_m, self.indices[keep])

    def column_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """Occupied voxels per (i, j) column: (M, 2) column indices and (M,) counts."""
        columns, counts = np.unique(self.indices[:, :2], axis=0, return_counts=True)
        return columns, counts


def voxel_indices(points: np.ndarray, origin_m: np.ndarray, resolution_m: float) -> np.ndarray:
    """Voxel (i, j, k) of each (N, 3) point under the half-open convention above."""
    return np.floor((points - origin_m) / resolution_m + _BOUNDARY_EPS).astype(np.int64)


def _lattice(n1: int, n2: int) -> np.ndarray:
    """(K, 2) weights (u, v) = (i/n1, j/n2) with u + v ≤ 1."""
    i, j = np.meshgrid(np.arange(n1 + 1), np.arange(n2 + 1), indexing="ij")
    u, v = i / n1, j / n2
    keep = u + v <= 1.0 + 1e-12
    return np.column_stack([u[keep], v[keep]])


_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


def _pack(indices: np.ndarray) -> np.ndarray:
    """One int64 key per (i, j, k) voxel index (each within ±2^20)."""
    shifted = indices + _KEY_OFFSET
    return (shifted[:, 0] << (2 * _KEY_BITS)) | (shifted[:, 1] << _KEY_BITS) | shifted[:, 2]


def _unpack(keys: np.ndarray) -> np.ndarray:
    mask = (1 << _KEY_BITS) - 1
    return (
        np.column_stack([(keys >> (2 * _KEY_BITS)) & mask, (keys >> _KEY_BITS) & mask, keys & mask])
        - _KEY_OFFSET
    )


def surface_voxels(
    mesh: WorldMesh,
    resolution_m: float,
    origin_m: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    *,
    surface_mask: np.ndarray | None = None,
    max_points_per_batch: int = 4_000_000,
) -> VoxelSet:
    """The voxels the mesh's surfaces pass through.

    ``surface_mask`` (bool per surface id) restricts the set to some surfaces, e.g. the static
    ones (``~mesh.surface_flags("movable")``).
    """
    if not (resolution_m > 0 and math.isfinite(resolution_m)):
        raise SensorError(f"resolution_m must be a positive number, got {resolution_m}")
    origin = np.asarray(origin_m, dtype=float).reshape(3)
    triangles = mesh.triangles
    if surface_mask is not None:
        triangles = triangles[np.asarray(surface_mask, dtype=bool)[mesh.triangle_surface]]
    corners = mesh.vertices[triangles]  # (T, 3, 3)
    # Span each triangle's lattice from its widest corner: its two edges are then as close to
    # perpendicular as the triangle allows, which keeps the lattice small for slivers.
    cosines = []
    for k in range(3):
        u = corners[:, (k + 1) % 3] - corners[:, k]
        v = corners[:, (k + 2) % 3] - corners[:, k]
        norms = np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1)
        cosines.append(np.abs(np.einsum("ij,ij->i", u, v)) / np.maximum(norms, 1e-300))
    apex = np.argmin(np.stack(cosines, axis=1), axis=1)
    rows = np.arange(len(corners))
    a = corners[rows, apex]
    b = corners[rows, (apex + 1) % 3]
    c = corners[rows, (apex + 2) % 3]
    e1, e2, e3 = b - a, c - a, c - b
    step = resolution_m / 4.0

    def count(edge: np.ndarray) -> np.ndarray:
        return np.maximum(1, np.ceil(np.linalg.norm(edge, axis=1) / step)).astype(np.int64)

    n1, n2, n3 = count(e1), count(e2), count(e3)
    keys: list[np.ndarray] = []
    pairs, group_of = np.unique(np.column_stack([n1, n2]), axis=0, return_inverse=True)
    for g, (m1, m2) in enumerate(pairs):
        members = np.flatnonzero(group_of.ravel() == g)
        weights = _lattice(int(m1), int(m2))
        per_batch = max(1, max_points_per_batch // len(weights))
        for start in range(0, len(members), per_batch):
            sel = members[start : start + per_batch]
            points = (
                a[sel, None, :]
                + weights[None, :, 0:1] * e1[sel, None, :]
                + weights[None, :, 1:2] * e2[sel, None, :]
            ).reshape(-1, 3)
            keys.append(np.unique(_pack(voxel_indices(points, origin, resolution_m))))
    # The lattice reaches the third edge only where its nodes fall on it: sample it as well.
    for m3 in np.unique(n3):
        sel = np.flatnonzero(n3 == m3)
        t = np.arange(int(m3) + 1)[None, :, None] / m3
        points = (b[sel, None, :] + t * e3[sel, None, :]).reshape(-1, 3)
        keys.append(np.unique(_pack(voxel_indices(points, origin, resolution_m))))
    if not keys:
        return VoxelSet(resolution_m, origin, np.zeros((0, 3), np.int64))
    return VoxelSet(resolution_m, origin, _unpack(np.unique(np.concatenate(keys))))


@dataclass(frozen=True)
class BandImage:
    """Per column of voxels, the occupied share of a height band: (H, W), row = y, col = x."""

    share: np.ndarray  # (H, W) in [0, 1]
    lower_xy: np.ndarray  # (2,) map-frame corner of cell (row 0, col 0)
    resolution_m: float

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) x and y of the cell centres."""
        rows, cols = self.share.shape
        xs = self.lower_xy[0] + (np.arange(cols) + 0.5) * self.resolution_m
        ys = self.lower_xy[1] + (np.arange(rows) + 0.5) * self.resolution_m
        gx, gy = np.meshgrid(xs, ys)
        return gx, gy

    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the image, for plotting."""
        rows, cols = self.share.shape
        x0, y0 = float(self.lower_xy[0]), float(self.lower_xy[1])
        return (x0, x0 + cols * self.resolution_m, y0, y0 + rows * self.resolution_m)


def band_share(
    voxels: VoxelSet,
    z_min_m: float,
    z_max_m: float,
    lower_xy: np.ndarray,
    upper_xy: np.ndarray,
) -> BandImage:
    """Sum the voxel columns of a height band and normalise (the paper's sub-ceiling section).

    A cell's value is the share of the band's voxel layers (those whose centres lie within
    [z_min_m, z_max_m)) that are occupied in its column. The image covers the voxel columns
    that overlap the rectangle [lower_xy, upper_xy], on the voxels' own lattice.
    """
    if not z_min_m < z_max_m:
        raise SensorError(f"band must run upwards, got [{z_min_m}, {z_max_m}]")
    res, origin = voxels.resolution_m, voxels.origin_m
    k_first = math.ceil((z_min_m - origin[2]) / res - 0.5 - _BOUNDARY_EPS)
    k_last = math.ceil((z_max_m - origin[2]) / res - 0.5 - _BOUNDARY_EPS) - 1
    layers = max(1, k_last - k_first + 1)
    first = np.floor((np.asarray(lower_xy, float) - origin[:2]) / res).astype(np.int64)
    last = np.floor((np.asarray(upper_xy, float) - origin[:2]) / res).astype(np.int64)
    cols, rows = (last - first + 1).tolist()
    share = np.zeros((max(rows, 0), max(cols, 0)))
    columns, counts = voxels.band(z_min_m, z_max_m).column_counts()
    if len(columns):
        ij = columns - first
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < cols) & (ij[:, 1] >= 0) & (ij[:, 1] < rows)
        share[ij[ok, 1], ij[ok, 0]] = counts[ok] / layers
    return BandImage(share, origin[:2] + first * res, res)
