"""coopmap estimation: mutual localization, the GTSAM pose graph, global localization, and the
application layer (configuration, pipelines, command line) that joins the three packages."""

from __future__ import annotations

from importlib import metadata

import sensors  # noqa: F401 - numba's cache folder, before any kernel (sensors.jitcache)

try:
    __version__ = metadata.version("coopmap")
except metadata.PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"
