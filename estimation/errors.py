"""Errors raised by the estimation core (mutual localization, pose graph, smoothers, metrics)."""

from __future__ import annotations

__all__ = ["EstimationError"]


class EstimationError(ValueError):
    """Bad input to, or failure of, an estimation step; the message names the bad value.

    Raised for degenerate mutual-localization geometry, NaN measurements, a pose graph with an
    unconstrained robot, corrupt trajectory or g2o files, a missing or corrupt checkpoint.
    """
