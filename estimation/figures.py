"""Figures (matplotlib, headless): worlds, simulated views.

Figures are drawn on ``matplotlib.figure.Figure`` objects with the Agg canvas — no pyplot state,
no display needed — and written atomically.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sensors.atomic import atomic_path
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.truth import band_share, surface_voxels
from sensors.sim.world import World

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ["render_range_panorama", "render_world"]

_DOOR_COLOR = "#e07b00"
_WINDOW_COLOR = "#2aa6d6"


def _new_figure(width_in: float, height_in: float) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width_in, height_in), dpi=110, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _save(figure: Figure, path: Path) -> None:
    with atomic_path(path) as tmp:
        figure.savefig(tmp, format="png")


def _draw_walls(ax: Axes, world: World) -> None:
    """Walls as black lines, doors and windows as coloured segments over their gaps."""
    for room in world.rooms:
        polygon = room.footprint_xy
        closed = np.vstack([polygon, polygon[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color="black", linewidth=1.2, zorder=3)
        for opening in room.openings:
            start, end = polygon[opening.wall], polygon[(opening.wall + 1) % len(polygon)]
            along = (end - start) / np.linalg.norm(end - start)
            a, b = start + opening.from_m * along, start + opening.to_m * along
            full_height = opening.is_door and opening.top_m >= room.ceiling_m - 1e-9
            color = "white" if full_height else _DOOR_COLOR if opening.is_door else _WINDOW_COLOR
            ax.plot(
                [a[0], b[0]],
                [a[1], b[1]],
                color=color,
                linewidth=3.0,
                zorder=4,
                solid_capstyle="butt",
            )


def _outline_flagged(ax: Axes, world: World) -> None:
    from matplotlib.patches import Circle, Polygon

    for box in world.boxes:
        if box.movable or box.retroreflective:
            ax.add_patch(
                Polygon(
                    box.corners_xy(),
                    closed=True,
                    fill=False,
                    zorder=5,
                    edgecolor="red" if box.retroreflective else "white",
                    linestyle="-" if box.retroreflective else "--",
                    linewidth=0.7,
                )
            )
    for cyl in world.cylinders:
        if cyl.movable or cyl.retroreflective:
            ax.add_patch(
                Circle(
                    (cyl.center[0], cyl.center[1]),
                    cyl.radius_m,
                    fill=False,
                    zorder=5,
                    edgecolor="red" if cyl.retroreflective else "white",
                    linestyle="-" if cyl.retroreflective else "--",
                    linewidth=0.7,
                )
            )


def render_world(
    world: World,
    path: Path | str,
    *,
    band_m: tuple[float, float] = (2.3, 2.9),
    band_resolution_m: float = 0.1,
    top_resolution_m: float = 0.05,
    cylinder_segments: int = 48,
) -> Path:
    """Two panels: the top view with a height colour scale, and the sub-ceiling band.

    The top view is the height of the highest surface under the ceilings, ray cast straight
    down; walls are black, doors orange, windows blue, movable objects dashed white outlines,
    retro-reflective ones red. The band panel is the ground-truth occupancy of the world between
    ``band_m`` heights at ``band_resolution_m``: per column, the share of the band that is
    occupied — what a perfect map's ceiling band would be.
    """
    path = Path(path)
    lower, upper = world.bounds_xy()
    margin = 0.5
    lower, upper = lower - margin, upper + margin
    scene = RaycastScene(build_mesh(world, cylinder_segments=cylinder_segments, ceilings=False))
    heights, _ = scene.height_map(lower, upper, top_resolution_m, world.max_ceiling_m + 1.0)

    mesh = build_mesh(world, cylinder_segments=cylinder_segments)
    voxels = surface_voxels(mesh, band_resolution_m)
    band_image = band_share(voxels, band_m[0], band_m[1], lower, upper)
    # Columns inside the rooms with nothing in the band are free (0); outside, unknown (NaN).
    gx, gy = band_image.cell_centers()
    inside = world.inside(np.column_stack([gx.ravel(), gy.ravel()])).reshape(gx.shape)
    band = np.where(inside | (band_image.share > 0), band_image.share, np.nan)

    extent_top = (
        lower[0],
        lower[0] + heights.shape[1] * top_resolution_m,
        lower[1],
        lower[1] + heights.shape[0] * top_resolution_m,
    )
    extent_band = band_image.extent()
    span = upper - lower
    wide = span[0] >= 1.3 * span[1]
    panel_w = 6.0 if wide else 5.0
    panel_h = panel_w * span[1] / span[0] + 0.9
    figure = (
        _new_figure(panel_w + 1.2, 2 * panel_h)
        if wide
        else _new_figure(2 * (panel_w + 1.2), panel_h)
    )
    axes = figure.subplots(2, 1) if wide else figure.subplots(1, 2)

    ax = axes[0]
    image = ax.imshow(
        heights,
        origin="lower",
        extent=extent_top,
        cmap="viridis",
        vmin=0.0,
        vmax=world.max_ceiling_m,
        interpolation="nearest",
    )
    _draw_walls(ax, world)
    _outline_flagged(ax, world)
    figure.colorbar(image, ax=ax, label="height of the top surface (m)", shrink=0.9)
    ax.set_title(f"{world.name}: top view")

    ax = axes[1]
    image = ax.imshow(
        band,
        origin="lower",
        extent=extent_band,
        cmap="Greys",
        vmin=0.0,
        vmax=1.0,
        interpolation="nearest",
    )
    _draw_walls(ax, world)
    figure.colorbar(image, ax=ax, label="occupied share of the band", shrink=0.9)
    ax.set_title(f"sub-ceiling band {band_m[0]:g}–{band_m[1]:g} m at {band_resolution_m:g} m")
    for ax in axes:
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")
        ax.set_xlim(lower[0], upper[0])
        ax.set_ylim(lower[1], upper[1])
    _save(figure, path)
    return path


def render_range_panorama(
    range_m: np.ndarray,
    azimuth_rad: np.ndarray,
    elevation_rad: np.ndarray,
    path: Path | str,
    *,
    title: str = "simulated 360° view",
) -> Path:
    """A (E, A) range image over azimuth and elevation, near returns light (paper Fig. 4b)."""
    path = Path(path)
    figure = _new_figure(10.0, 3.6)
    ax = figure.subplots()
    shown = np.where(np.isfinite(range_m), range_m, np.nan)
    step_az = float(np.degrees(azimuth_rad[1] - azimuth_rad[0])) if len(azimuth_rad) > 1 else 1.0
    step_el = (
        float(np.degrees(elevation_rad[1] - elevation_rad[0])) if len(elevation_rad) > 1 else 1.0
    )
    extent = (
        np.degrees(azimuth_rad[0]) - step_az / 2,
        np.degrees(azimuth_rad[-1]) + step_az / 2,
        np.degrees(elevation_rad[0]) - step_el / 2,
        np.degrees(elevation_rad[-1]) + step_el / 2,
    )
    # Azimuth grows to the left (counter-clockwise), as the robot sees it.
    image = ax.imshow(
        shown[:, ::-1],
        origin="lower",
        aspect="auto",
        cmap="magma_r",
        extent=(extent[1], extent[0], extent[2], extent[3]),
        interpolation="nearest",
    )
    figure.colorbar(image, ax=ax, label="range (m)")
    ax.set_xlabel("azimuth (deg, counter-clockwise from forward)")
    ax.set_ylabel("elevation (deg)")
    ax.set_title(title)
    _save(figure, path)
    return path
