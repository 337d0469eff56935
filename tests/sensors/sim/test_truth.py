"""Ground-truth occupancy against analytic voxel counts."""

from __future__ import annotations

import numpy as np
import pytest

from sensors.errors import SensorError
from sensors.sim.scene import build_mesh
from sensors.sim.truth import band_share, surface_voxels
from sensors.sim.world import World, world_from_mapping
from tests.sensors.sim.conftest import box_room_document


def shell(nx: int, ny: int, nz: int) -> int:
    """Voxels on the surface of an nx × ny × nz block of voxels."""
    return nx * ny * nz - (nx - 2) * (ny - 2) * (nz - 2)


@pytest.mark.parametrize(
    "origin",
    [(0.0, 0.0, 0.0), (-0.05, -0.05, -0.05), (0.03, 0.02, 0.01), (-0.1, 0.2, -0.3)],
)
def test_box_room_voxel_count_is_analytic(box_room: World, origin: tuple[float, ...]) -> None:
    # Walls at x = 0 and 4, y = 0 and 3, floor 0, ceiling 2.5, at 0.1 m: on every lattice the
    # room's surfaces fill a shell 41 × 31 × 26 voxels large.
    voxels = surface_voxels(build_mesh(box_room), 0.1, origin)
    assert len(voxels) == shell(41, 31, 26) == 5902
    assert len(np.unique(voxels.indices, axis=0)) == len(voxels)


def test_box_room_voxels_sit_on_the_surfaces(box_room: World) -> None:
    voxels = surface_voxels(build_mesh(box_room), 0.1)
    centers = voxels.centers()
    # Each voxel centre lies within half a voxel (plus boundary rounding) of a room plane.
    gaps = np.min(np.abs(np.concatenate([centers, [4.0, 3.0, 2.5] - centers], axis=1)), axis=1)
    assert gaps.max() <= 0.05 + 1e-9
    lower = voxels.indices.min(axis=0)
    upper = voxels.indices.max(axis=0)
    assert lower.tolist() == [0, 0, 0]
    assert upper.tolist() == [40, 30, 25]


def test_surface_mask_selects_surfaces() -> None:
    doc = box_room_document()
    doc["boxes"] = [{"name": "crate", "center": [2.05, 1.55], "size": [0.4, 0.4], "z_m": [0, 1]}]
    mesh = build_mesh(world_from_mapping(doc))
    crate_only = np.array([s.name == "crate" for s in mesh.surfaces])
    # x 1.85–2.25 → cells 18–22, y 1.35–1.75 → 13–17, z 0–1 → 0–10: a 5 × 5 × 11 shell.
    assert len(surface_voxels(mesh, 0.1, surface_mask=crate_only)) == shell(5, 5, 11)
    floor_only = np.array([s.kind == "floor" for s in mesh.surfaces])
    floor = surface_voxels(mesh, 0.1, surface_mask=floor_only)
    assert len(floor) == 41 * 31
    assert set(floor.indices[:, 2]) == {0}


def test_band_and_column_counts(box_room: World) -> None:
    voxels = surface_voxels(build_mesh(box_room), 0.1)
    band = voxels.band(2.3, 2.9)
    # Layers with centres 2.35 and 2.45 are wall rings; the ceiling layer (2.55) is full.
    ring = 2 * 41 + 2 * 29
    assert len(band) == 2 * ring + 41 * 31
    columns, counts = band.column_counts()
    assert len(columns) == 41 * 31
    assert counts.max() == 3
    assert counts.min() == 1


def test_resolution_must_be_positive(box_room: World) -> None:
    mesh = build_mesh(box_room)
    for bad in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(SensorError, match="resolution_m must be a positive number"):
            surface_voxels(mesh, bad)


def test_finer_resolution_scales_with_area(box_room: World) -> None:
    coarse = len(surface_voxels(build_mesh(box_room), 0.1))
    fine = len(surface_voxels(build_mesh(box_room), 0.05))
    assert fine == shell(81, 61, 51)
    assert 3.5 < fine / coarse < 4.5  # surfaces: voxel count grows with 1 / res²


def test_band_share_of_a_room_with_a_beam() -> None:
    doc = box_room_document()
    doc["boxes"] = [{"name": "beam", "center": [2.05, 1.5], "size": [0.2, 3.0], "z_m": [2.3, 2.5]}]
    voxels = surface_voxels(build_mesh(world_from_mapping(doc)), 0.1)
    image = band_share(voxels, 2.0, 2.4, np.array([-0.5, -0.5]), np.array([4.5, 3.5]))
    # Layers with centres 2.05, 2.15, 2.25, 2.35: four; the ceiling (2.55) is above the band.
    assert image.share.shape == (41, 51)
    assert image.extent() == pytest.approx((-0.5, 4.6, -0.5, 3.6))
    gx, gy = image.cell_centers()
    at = lambda x, y: image.share[np.argmin(np.abs(gy[:, 0] - y)), np.argmin(np.abs(gx[0] - x))]  # noqa: E731
    assert at(0.05, 1.55) == 1.0  # a wall column: all four layers
    assert at(1.05, 1.55) == 0.0  # open room
    assert at(1.95, 1.55) == 0.25  # the beam's side face: only the 2.35 layer
    assert at(2.05, 1.55) == 0.25  # the beam's underside at 2.3: the 2.35 layer
    assert at(-0.45, 1.55) == 0.0  # outside: nothing
    assert image.share.max() == 1.0


def test_band_share_rejects_an_upside_down_band(box_room: World) -> None:
    voxels = surface_voxels(build_mesh(box_room), 0.1)
    with pytest.raises(SensorError, match="band must run upwards"):
        band_share(voxels, 2.9, 2.3, np.zeros(2), np.ones(2))
