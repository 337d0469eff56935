"""The simulator: worlds, their meshes and ray casting, ground truth, and simulated sensing."""
