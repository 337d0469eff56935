"""Figures (matplotlib, headless): worlds, simulated views, and a result's figures — the ceiling
band with the trajectories, the occupied cells (paper Fig. 5a), one measured sweep (Fig. 4b) and
the position PDFs of the searches (Fig. 5b).

Figures are drawn on ``matplotlib.figure.Figure`` objects with the Agg canvas — no pyplot state,
no display needed — and written atomically.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from sensors.atomic import atomic_path
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.truth import band_share, surface_voxels
from sensors.sim.world import World

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "draw_band",
    "draw_scan_at",
    "render_map_cubes",
    "render_range_panorama",
    "render_search_pdf",
    "render_sweep",
    "render_trajectories",
    "render_world",
]

_DOOR_COLOR = "#e07b00"
_WINDOW_COLOR = "#2aa6d6"
#: Facets per side of a PDF surface at most.
_FACETS = 80


def _new_figure(
    width_in: float, height_in: float, layout: Literal["constrained"] | None = "constrained"
) -> Figure:
    """A figure on the Agg canvas; ``layout`` None places the axes where they are added (the
    constrained layout measures every label once more, a third of a simple figure's time)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width_in, height_in), dpi=110, layout=layout)
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


_ROBOT_COLORS = ("#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e")


def draw_band(ax: Axes, band: Any) -> Any:
    """A band (``mapping.band.Band``) on ``ax`` in metres: occupied dark, observed free white,
    unknown in ``mapping.figures.UNKNOWN_COLOR``; returns the image (for a colour bar)."""
    from mapping.figures import band_shading

    shade, colors = band_shading(band)
    return ax.imshow(shade, origin="lower", extent=band.extent(), cmap=colors, vmin=0.0,
                     vmax=1.0, interpolation="nearest")  # fmt: skip


def draw_scan_at(ax: Axes, scan: Any, pose: np.ndarray, **style: Any) -> None:
    """The occupied cells of a band ``scan`` (in its own frame) drawn at ``pose`` (x, y, yaw)."""
    gx, gy = scan.cell_centers()
    occupied = scan.known & (scan.occupancy >= 0.5)
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    px = c * gx[occupied] - s * gy[occupied] + float(pose[0])
    py = s * gx[occupied] + c * gy[occupied] + float(pose[1])
    ax.scatter(px, py, s=2, linewidths=0, **({"c": "tab:red"} | style))


def _band_colorbar(figure: Figure, ax: Axes, image: Any, cax: Axes | None = None) -> None:
    bar = (figure.colorbar(image, ax=ax, shrink=0.8, pad=0.01) if cax is None
           else figure.colorbar(image, cax=cax))  # fmt: skip
    bar.set_ticks([0.0, 0.5, 1.0], labels=["occupied", "half", "free"])
    bar.set_label("band: share of layers free (blue-grey: unknown)")


def render_trajectories(
    band: Any,
    poses: dict[str, dict[int, np.ndarray]],
    path: Path | str,
    *,
    truth: dict[str, dict[int, np.ndarray]] | None = None,
    world: World | None = None,
    title: str = "ceiling band and stations",
) -> Path:
    """A 2D band (``mapping.band.Band``: unknown drawn apart from free) with each robot's poses:
    the estimate, and the truth and the true world's walls if given."""
    path = Path(path)
    x0, x1, y0, y1 = band.extent()
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    figure = _new_figure(8.0, max(3.0, 8.0 * aspect) + 0.6)
    ax = figure.subplots()
    _band_colorbar(figure, ax, draw_band(ax, band))
    if world is not None:
        _draw_walls(ax, world)
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
    for n, (robot, robot_poses) in enumerate(sorted(poses.items())):
        color = _ROBOT_COLORS[n % len(_ROBOT_COLORS)]
        order = sorted(robot_poses)
        xy = np.array([robot_poses[i][:2] for i in order]).reshape(-1, 2)
        yaw = np.array([robot_poses[i][2] for i in order])
        ax.plot(xy[:, 0], xy[:, 1], "-o", color=color, markersize=4, label=f"{robot} (estimate)")
        ax.quiver(xy[:, 0], xy[:, 1], np.cos(yaw), np.sin(yaw), color=color, scale=25, width=0.004)
        if truth is not None and robot in truth:
            t = np.array([truth[robot][i][:2] for i in order if i in truth[robot]]).reshape(-1, 2)
            ax.plot(t[:, 0], t[:, 1], "x--", color=color, alpha=0.6, label=f"{robot} (truth)")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=7)
    _save(figure, path)
    return path


def render_sweep(
    points_scanner: np.ndarray,
    path: Path | str,
    *,
    beacons: np.ndarray | None = None,
    title: str = "one measured sweep",
    max_points: int = 40_000,
) -> Path:
    """One 3D scan as measured (paper Fig. 4b): its returns in the scanner frame seen from above
    at an angle, coloured by their distance from the scanner; beacon detections ringed."""
    from mpl_toolkits.mplot3d import Axes3D  # noqa: F401 - registers the 3d projection

    path = Path(path)
    points = np.asarray(points_scanner, dtype=np.float64).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    total = len(points)
    if total > max_points:  # every k-th return: the sweep's structure, not a random subset
        points = points[:: math.ceil(total / max_points)]
    distance = np.linalg.norm(points, axis=1)
    figure = _new_figure(9.0, 6.5)
    ax = figure.add_subplot(projection="3d")
    if len(points):
        scatter = ax.scatter(points[:, 0], points[:, 1], points[:, 2], c=distance, cmap="turbo",
                             s=0.6, linewidths=0, depthshade=False)  # fmt: skip
        figure.colorbar(scatter, ax=ax, shrink=0.6, pad=0.08, label="distance from scanner (m)")
        span = np.ptp(points, axis=0)
        ax.set_box_aspect((max(span[0], 1e-3), max(span[1], 1e-3), max(span[2], 1e-3)))
    if beacons is not None and len(beacons):
        b = np.asarray(beacons, dtype=np.float64).reshape(-1, 3)
        ax.scatter(b[:, 0], b[:, 1], b[:, 2], s=90, facecolors="none", edgecolors="magenta",
                   linewidths=1.5, label="beacon detection")  # fmt: skip
        ax.legend(loc="upper left", fontsize=7)
    ax.view_init(elev=50, azim=-70)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    shown = f"{len(points):,} of {total:,} returns" if total > len(points) else f"{total:,} returns"
    ax.set_title(f"{title}: {shown}")
    _save(figure, path)
    return path


def _block_max(values: np.ndarray, step_y: int, step_x: int) -> np.ndarray:
    """The maximum of each ``step_y`` × ``step_x`` block of ``values`` (2D; partial blocks at
    the ends), one value per block."""
    if values.size == 0 or (step_y == 1 and step_x == 1):
        return values
    h, w = values.shape
    rows = np.maximum.reduceat(values, np.arange(0, h, step_y), axis=0)
    return np.maximum.reduceat(rows, np.arange(0, w, step_x), axis=1)


def render_search_pdf(picture: Any, pose: np.ndarray, path: Path | str, *, title: str) -> Path:
    """A search's position PDF (paper Fig. 5b): P(x, y) summed over the rotations as a surface
    over the window searched, beside the map searched with the local band's occupied cells at the
    best pose and the window outlined. ``picture`` is an
    ``estimation.search.records.SearchPicture``; ``pose`` the best pose in its map's frame."""
    from mpl_toolkits.mplot3d import Axes3D  # noqa: F401 - registers the 3d projection

    path = Path(path)
    marginal = np.asarray(picture.marginal, dtype=np.float64)
    peak = float(marginal.max()) if marginal.size else 0.0
    relative = marginal / peak if peak > 0 else marginal
    # At most _FACETS × _FACETS facets, each the highest of the positions it covers (a stride
    # could step over a sharp peak): the surface's shape, drawn in a fraction of a second.
    step_y = max(1, math.ceil(relative.shape[0] / _FACETS))
    step_x = max(1, math.ceil(relative.shape[1] / _FACETS))
    xs, ys = picture.x_m[::step_x], picture.y_m[::step_y]
    surface = _block_max(relative, step_y, step_x)
    # Placed by hand: a result draws six of these, and the constrained layout cost 40 % more.
    figure = _new_figure(13.0, 5.6, layout=None)
    ax_pdf: Any = figure.add_axes((0.0, 0.02, 0.47, 0.84), projection="3d")
    if surface.size:
        gx, gy = np.meshgrid(xs, ys)
        ax_pdf.plot_surface(gx, gy, surface, cmap="viridis", linewidth=0, antialiased=False,
                            rstride=1, cstride=1)  # fmt: skip
    ax_pdf.set_xlabel("x (m)")
    ax_pdf.set_ylabel("y (m)")
    ax_pdf.set_zlabel("P(x, y) / max")
    ax_pdf.view_init(elev=35, azim=-60)
    ax_pdf.set_title(f"position PDF over {len(picture.x_m)} × {len(picture.y_m)} positions")
    ax_map = figure.add_axes((0.53, 0.1, 0.34, 0.76))
    image = draw_band(ax_map, picture.against)
    _band_colorbar(figure, ax_map, image, figure.add_axes((0.895, 0.16, 0.012, 0.64)))
    draw_scan_at(ax_map, picture.local, pose, label="local band: occupied cells")
    if len(picture.x_m) and len(picture.y_m):
        wx = (float(picture.x_m[0]), float(picture.x_m[-1]))
        wy = (float(picture.y_m[0]), float(picture.y_m[-1]))
        ax_map.plot([wx[0], wx[1], wx[1], wx[0], wx[0]], [wy[0], wy[0], wy[1], wy[1], wy[0]],
                    "--", color="tab:orange", lw=1, label="window searched")  # fmt: skip
    x, y, yaw = (float(v) for v in pose)
    ax_map.plot([x], [y], marker="o", ms=9, mfc="none", mec="tab:cyan", mew=2)
    ax_map.annotate("", xy=(x + 0.8 * math.cos(yaw), y + 0.8 * math.sin(yaw)), xytext=(x, y),
                    arrowprops={"arrowstyle": "->", "color": "tab:cyan", "lw": 2})  # fmt: skip
    ax_map.set_aspect("equal")
    ax_map.set_xlabel("x (m)")
    ax_map.set_ylabel("y (m)")
    ax_map.legend(loc="upper right", fontsize=7, markerscale=4)
    ax_map.set_title(f"best pose x={x:.2f} m, y={y:.2f} m, yaw={math.degrees(yaw):.1f}°")
    figure.suptitle(title, y=0.97)
    _save(figure, path)
    return path


def render_map_cubes(grid: Any, path: Path | str, *, threshold: float = 0.9,
                     z_range_m: tuple[float, float] = (0.05, 2.9),
                     max_cubes: int = 60_000) -> Path:  # fmt: skip
    """Occupied cells (P > ``threshold``) between floor and ceiling as cubes seen from above at an
    angle (the paper's Fig. 5a draws the space 1–2.9 m above the floor)."""
    from mpl_toolkits.mplot3d import Axes3D  # noqa: F401 - registers the 3d projection

    path = Path(path)
    cells, _ = grid.occupied(threshold)
    centers = grid.cell_centers(cells) if len(cells) else np.zeros((0, 3))
    centers = centers[(centers[:, 2] >= z_range_m[0]) & (centers[:, 2] < z_range_m[1])]
    if len(centers) > max_cubes:
        centers = centers[np.random.default_rng(0).choice(len(centers), max_cubes, replace=False)]
    figure = _new_figure(9.0, 6.5)
    ax = figure.add_subplot(projection="3d")
    if len(centers):
        size = 20 * grid.resolution_m / 0.1
        ax.scatter(centers[:, 0], centers[:, 1], centers[:, 2], c=centers[:, 2], cmap="viridis",
                   marker="s", s=size, depthshade=True, linewidths=0)  # fmt: skip
        span = np.ptp(centers, axis=0)
        ax.set_box_aspect((max(span[0], 1e-3), max(span[1], 1e-3), max(span[2], 1e-3)))
    ax.view_init(elev=55, azim=-60)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title(
        f"occupied cells (P > {threshold:g}) at {z_range_m[0]:g}–{z_range_m[1]:g} m: "
        f"{len(centers):,}"
    )
    _save(figure, path)
    return path
