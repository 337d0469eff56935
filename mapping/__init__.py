"""coopmap mapping: 3D Bayesian occupancy grids, 2D bands and map file formats.

* ``mapping.grid`` — ``OccupancyGrid`` (log-odds in blocks that grow on demand; scan
  integration by exact voxel traversal in numba kernels, ``mapping.kernels``) and
  ``GridParams``; ``mapping.logodds`` — the paper's eq. 3 and its log-odds form.
* ``mapping.fusion`` — fusing raw scans at given poses (local and global maps), moving grids
  between frames, merging grids.
* ``mapping.band`` — 2D grids from height bands (the paper's sub-ceiling section).
* Formats: ``mapping.formats.npz`` (native, versioned, lossless), ``mapping.formats.ply`` (point
  clouds and occupied voxels), ``mapping.formats.pgm`` (ROS map_server),
  ``mapping.formats.octomap_bt`` (OctoMap ``.bt``); ``mapping.figures`` draws bands.

Every error is a ``mapping.errors.MapError``.
"""

import sensors  # noqa: F401 - numba's cache folder, before any kernel (sensors.jitcache)
