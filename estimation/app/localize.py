"""``coopmap localize``: global localization of a scan grid in a map, both ROS map_server files.

Glue between the configuration, the map_server reader of ``mapping.formats.pgm`` and the search of
``estimation.search.exhaustive``: read both grids, search the whole map (or, given a prior position,
a window around it that grows until the peak is dominant), and report the pose of the scan grid's
frame in the map frame with the fields of docs/design.md §11; optionally draw the position PDF.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from estimation.app.config import ConfigError, SearchConfig
from estimation.app.rig import search_params
from estimation.search.exhaustive import (
    MAX_PDF_POSES,
    SearchResult,
    WindowStep,
    search,
    windowed_search,
)
from estimation.search.lattice import pose_lattice, yaw_lattice
from estimation.search.pyramid import TiledResult, search_coarse_to_fine
from mapping.band import Band
from mapping.formats.pgm import read_band_pgm
from sensors.atomic import atomic_path

__all__ = ["Localization", "localize_files", "render_pdf"]


@dataclass(frozen=True)
class Localization:
    """A localization: the search's answer (the whole PDF, or coarse to fine on a map whose
    whole PDF does not fit), the windows it took, and the two grids."""

    result: SearchResult | TiledResult
    windows: tuple[WindowStep, ...]
    dominant: bool
    map_band: Band
    scan_band: Band
    seconds: float  # reading excluded

    def as_json(self) -> dict[str, Any]:
        """docs/design.md §11's fields, plus the dominance verdict and the windows searched."""
        x, y, yaw = (float(v) for v in self.result.pose)
        return {
            "x_m": x,
            "y_m": y,
            "yaw_deg": math.degrees(yaw),
            "cov": [[float(v) for v in row] for row in self.result.covariance],
            "peak_ratio": _finite(self.result.peak_ratio),
            "seconds": self.seconds,
            "dominant": self.dominant,
            "windows_m": [w.side_m for w in self.windows],
            "poses_searched": self.result.poses,
            "poses_at_full_resolution": (
                self.result.poses_evaluated
                if isinstance(self.result, TiledResult)
                else self.result.poses
            ),
            "unevaluated_mass": (
                self.result.unevaluated_mass if isinstance(self.result, TiledResult) else 0.0
            ),
        }


def _finite(value: float) -> float | None:
    """JSON has no infinity: a peak with nothing elsewhere reports null."""
    return float(value) if math.isfinite(value) else None


def localize_files(
    map_yaml: Path,
    scan_yaml: Path,
    config: SearchConfig,
    *,
    prior: tuple[float, float, float] | None = None,
    window_m: float | None = None,
) -> Localization:
    """Localize the scan grid in the map grid.

    Without a prior the whole map is searched: every pose, or coarse to fine
    (``search_coarse_to_fine``) when the whole PDF would exceed ``MAX_PDF_POSES``. With
    ``prior`` (x_m, y_m, yaw_deg) a square window of side ``window_m`` (default
    ``config.window_m``) centred on the prior position is searched, doubling until the peak is
    dominant, the map is covered or the side reaches ``config.max_window_m``; every rotation
    is searched either way (the prior yaw is not used).
    """
    if window_m is not None and prior is None:
        raise ConfigError("--window-m needs --prior: the window is centred on the prior position")
    if window_m is not None and not (math.isfinite(window_m) and window_m > 0):
        raise ConfigError(f"--window-m must be a positive number of metres, got {window_m}")
    map_band = read_band_pgm(map_yaml)
    scan_band = read_band_pgm(scan_yaml)
    params = search_params(config)
    started = time.perf_counter()
    if prior is None:
        x_m, y_m, _ = pose_lattice(scan_band, map_band)
        poses = len(x_m) * len(y_m) * len(yaw_lattice(params.angular_resolution_rad))
        result: SearchResult | TiledResult
        if poses > MAX_PDF_POSES:
            result = search_coarse_to_fine(scan_band, map_band, params)
        else:
            result = search(scan_band, map_band, params)
        windows: tuple[WindowStep, ...] = ()
        dominant = result.is_dominant(params.dominance_ratio)
    else:
        side = config.window_m if window_m is None else window_m
        found = windowed_search(
            scan_band,
            map_band,
            params,
            prior[:2],
            side,
            max(side, config.max_window_m),
        )
        result, windows, dominant = found.result, found.steps, found.dominant
    return Localization(
        result=result,
        windows=windows,
        dominant=dominant,
        map_band=map_band,
        scan_band=scan_band,
        seconds=time.perf_counter() - started,
    )


def render_pdf(localization: Localization, path: Path) -> Path:
    """Three panels: the map with the scan's occupied cells drawn at the best pose; the position
    PDF summed over rotations (the paper's Fig. 5b) as a log-scale heat map; and a linear close
    view of the peak, ±1 m around the best pose. The best pose is marked on each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from estimation.app.figures import draw_band, draw_scan_at

    result = localization.result
    band, scan = localization.map_band, localization.scan_band
    x, y, yaw = (float(v) for v in result.pose)
    x0, x1, y0, y1 = band.extent()
    wide = (x1 - x0) > 1.6 * (y1 - y0)
    if wide:
        fig = plt.figure(figsize=(12, 13), constrained_layout=True)
        grid = fig.add_gridspec(3, 1, height_ratios=[1.0, 1.0, 1.3])
    else:
        fig = plt.figure(figsize=(19, 6.5), constrained_layout=True)
        grid = fig.add_gridspec(1, 3, width_ratios=[1.0, 1.0, 0.8])
    ax_map, ax_pdf, ax_zoom = (fig.add_subplot(grid[i]) for i in range(3))

    draw_band(ax_map, band)
    draw_scan_at(ax_map, scan, result.pose, label="scan: occupied cells")
    c, s = math.cos(yaw), math.sin(yaw)
    ax_map.set_title("map (white: free; blue-grey: unknown), scan placed at the best pose")
    ax_map.legend(loc="upper right", markerscale=4)

    marginal = result.position_marginal()
    step_x, step_y = result.x_m[1] - result.x_m[0], result.y_m[1] - result.y_m[0]
    extent = (
        result.x_m[0] - step_x / 2,
        result.x_m[-1] + step_x / 2,
        result.y_m[0] - step_y / 2,
        result.y_m[-1] + step_y / 2,
    )
    with np.errstate(divide="ignore"):
        decades = np.maximum(np.log10(marginal / marginal.max()), -12.0)
    image = ax_pdf.imshow(decades, origin="lower", extent=extent, cmap="magma", vmin=-12, vmax=0)
    fig.colorbar(image, ax=ax_pdf, shrink=0.8, label="log10 P(x, y) / max")
    ax_pdf.set_title(
        f"position PDF (summed over {len(result.yaw_rad)} rotations); peak ratio "
        f"{result.peak_ratio:.3g}"
    )

    ix = np.flatnonzero(np.abs(result.x_m - x) <= 1.0)
    iy = np.flatnonzero(np.abs(result.y_m - y) <= 1.0)
    close = marginal[np.ix_(iy, ix)]
    zoom = ax_zoom.imshow(
        close / marginal.max(),
        origin="lower",
        extent=(
            result.x_m[ix[0]] - step_x / 2,
            result.x_m[ix[-1]] + step_x / 2,
            result.y_m[iy[0]] - step_y / 2,
            result.y_m[iy[-1]] + step_y / 2,
        ),
        cmap="viridis",
        vmin=0,
        vmax=1,
    )
    fig.colorbar(zoom, ax=ax_zoom, shrink=0.8, label="P(x, y) / max")
    sigma = np.sqrt(np.maximum(np.diag(result.covariance), 0.0))
    ax_zoom.set_title(
        f"peak: x={x:.3f} m, y={y:.3f} m, yaw={math.degrees(yaw):.2f}°\n"
        f"σ {sigma[0] * 100:.1f} cm, {sigma[1] * 100:.1f} cm, {math.degrees(sigma[2]):.2f}°"
    )
    for ax, arrow in ((ax_map, 0.8), (ax_pdf, 0.8), (ax_zoom, 0.3)):
        ax.plot([x], [y], marker="o", ms=9, mfc="none", mec="tab:cyan", mew=2)
        ax.annotate(
            "",
            xy=(x + arrow * c, y + arrow * s),
            xytext=(x, y),
            arrowprops={"arrowstyle": "->", "color": "tab:cyan", "lw": 2},
        )
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    return path
