"""numba kernels of the occupancy grid (``mapping.grid``), one module per concern.

* ``blocks`` — block keys, the in-block layout, the block hash table, the addressable range.
* ``cube`` — the scan's Morton-ordered de-duplication bitmap around the sensor.
* ``traversal`` — voxel traversal of rays: the in-cube fast path and the general per-cell path.
* ``integrate`` — one scan into the grid, resumable when the block pool is full.
* ``cells`` — per-cell and per-block kernels: adding evidence, lookup, merging, resampling.

Each module imports only modules listed above it. Nothing is re-exported here: import from
the modules.
"""
