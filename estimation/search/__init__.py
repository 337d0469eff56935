"""Global localization: the (x, y, θ) search of a local band grid against a map (docs/design.md §7).

Modules, each importing only those before it:

* ``lattice``: the metric (cell values) and the pose lattice, shared by both searches;
* ``correlate``: the scores of every pose, by FFT correlation, and the per-pose loop;
* ``peak``: the normalised PDF of the scores, the peak's dominance, covariance and refinement;
* ``bnb_bounds``, ``bnb``: the best lattice pose alone, by branch and bound;
* ``exhaustive``: ``search`` (every pose, the whole PDF), ``best_pose``, ``windowed_search``;
* ``pyramid``: ``search_coarse_to_fine``, for lattices whose whole PDF does not fit;
* ``scenes``: synthetic buildings and local views for tests and benchmarks;
* ``stations``: relocalization at the reference stations of a mission.
"""
