"""Errors raised by the ``mapping`` package."""

from __future__ import annotations

__all__ = ["MapError"]


class MapError(ValueError):
    """Base of every error the ``mapping`` package raises on bad input or a bad map file.

    The message names the file (where there is one) and the offending value.
    """
