"""The seed hook (docs/design.md §5): a new station's initial value from a search result.

A search PDF seeds a station only when its peak is dominant — the best pose beats the best pose
elsewhere by ``dominance_ratio`` — otherwise the fallback (odometry or mutual localization) is
kept. Poses are in the PDF's own frame (the map, or the reference station).
"""

from __future__ import annotations

import numpy as np

from estimation.posepdf import PosePdf

__all__ = ["seed_pose"]


def seed_pose(
    pdf: PosePdf,
    fallback: np.ndarray | None,
    dominance_ratio: float,
    peak_radius_m: float,
    peak_radius_rad: float,
) -> tuple[np.ndarray | None, bool]:
    """(initial pose, whether it came from the search).

    The search's refined best pose when ``pdf``'s peak is dominant, else ``fallback`` (which may
    be None when nothing else knows the pose).
    """
    if pdf.is_dominant(dominance_ratio, peak_radius_m, peak_radius_rad):
        return pdf.best_pose(), True
    return (None if fallback is None else np.asarray(fallback, dtype=float).copy()), False
