"""Figures of maps (matplotlib, headless, imported only when drawing; written atomically)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mapping.band import Band
from sensors.atomic import atomic_path

__all__ = ["UNKNOWN_COLOR", "band_shading", "render_band"]

#: Unknown cells are drawn in this colour: never white, which is free.
UNKNOWN_COLOR = "#b9c4cc"


def band_shading(band: Band) -> tuple[np.ndarray, Any]:
    """The image and colour map that draw a band: occupied dark, observed free white, unknown
    in ``UNKNOWN_COLOR``; the image runs from 0 (occupied) to 1 (free)."""
    from matplotlib.colors import ListedColormap

    shade = np.where(band.known, 1.0 - band.occupancy, np.nan)
    colors = ListedColormap(np.linspace(0.0, 1.0, 256)[:, None].repeat(3, axis=1))
    return shade, colors.with_extremes(bad=UNKNOWN_COLOR)


def render_band(band: Band, path: Path | str, *, title: str = "") -> Path:
    """Draw a 2D band as an image — occupied share dark, observed free light, unknown grey —
    in metres of the map frame, and write it as a PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    rows, cols = band.shape
    width = 9.0
    height = max(2.5, min(9.0, width * rows / max(cols, 1) + 1.2))
    figure = Figure(figsize=(width, height), dpi=120, layout="constrained")
    FigureCanvasAgg(figure)
    ax = figure.add_subplot()
    shade, colors = band_shading(band)
    image = ax.imshow(
        shade, origin="lower", extent=band.extent(), cmap=colors, vmin=0.0, vmax=1.0,
        interpolation="nearest",
    )  # fmt: skip
    bar = figure.colorbar(image, ax=ax, shrink=0.8, pad=0.01)
    bar.set_ticks([0.0, 0.5, 1.0], labels=["occupied", "half", "free"])
    bar.set_label("share of the band's layers free (grey: unknown)")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    if title:
        ax.set_title(title, fontsize=10)
    with atomic_path(path) as tmp:
        figure.savefig(tmp, format="png")
    return path
