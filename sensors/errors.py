"""Errors raised by the ``sensors`` package."""

from __future__ import annotations

__all__ = [
    "DeviceError",
    "OutputError",
    "RecordingError",
    "SensorError",
    "TrajectoryError",
    "WorldError",
]


class SensorError(Exception):
    """Base of every error the ``sensors`` package raises on bad input or device trouble."""


class WorldError(SensorError, ValueError):
    """A world description is invalid; the message names the file, key path and value."""


class DeviceError(SensorError):
    """A device (the LMS 200 on its serial port) failed; the message says what was happening."""


class TrajectoryError(SensorError, ValueError):
    """A trajectory or pose-graph file (TUM, g2o, CARMEN log) is malformed; the message names the
    file, the line and what is wrong."""


class OutputError(SensorError):
    """An output path coopmap must not write to (a user's folder, the input itself, a file)."""


class RecordingError(SensorError):
    """A recording cannot be made or read (clock server, odometry source, recording folder); the
    message names the endpoint or file."""
