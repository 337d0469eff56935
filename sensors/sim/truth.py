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

__all__ = ["VoxelSet", "surface_voxels"]

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


def _barycentric_lattice(n: int) -> np.ndarray:
    """(K, 2) weights (u, v) with u, v ∈ {0, 1/n, …, 1}, u + v ≤ 1."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    return np.column_stack([i[keep], j[keep]]).astype(float) / n


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
    a, b, c = (mesh.vertices[triangles[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    longest = np.max(
        np.stack([np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1),
                  np.linalg.norm(c - b, axis=1)]),
        axis=0,
    )
    step = resolution_m / 4.0
    subdivisions = np.maximum(1, np.ceil(longest / step)).astype(np.int64)

    found: list[np.ndarray] = []
    for n in np.unique(subdivisions):
        group = np.flatnonzero(subdivisions == n)
        weights = _barycentric_lattice(int(n))
        per_batch = max(1, max_points_per_batch // len(weights))
        for start in range(0, len(group), per_batch):
            rows = group[start : start + per_batch]
            points = (
                a[rows, None, :]
                + weights[None, :, 0:1] * e1[rows, None, :]
                + weights[None, :, 1:2] * e2[rows, None, :]
            ).reshape(-1, 3)
            found.append(np.unique(voxel_indices(points, origin, resolution_m), axis=0))
    indices = np.unique(np.concatenate(found), axis=0) if found else np.zeros((0, 3), np.int64)
    return VoxelSet(resolution_m, origin, indices)
