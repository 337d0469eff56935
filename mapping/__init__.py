"""coopmap mapping: 3D Bayesian occupancy grids, 2D bands and map file formats."""
