"""Factor specifications as native GTSAM factors and values (gtsam is imported only here and in
the smoother, inside the functions that need it)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

import numpy as np

from estimation.chi2 import chi2_quantile
from estimation.posegraph.graph import FactorSpec, RobustKernel

if TYPE_CHECKING:
    import gtsam

__all__ = ["to_gtsam_factor", "to_gtsam_graph", "to_gtsam_values"]

#: Robust kernels act on the norm of the whitened 3-vector: their width is its 95 % quantile.
_KERNEL_WIDTH = math.sqrt(chi2_quantile(0.95, 3))


def to_gtsam_factor(spec: FactorSpec, kernel: RobustKernel = "none") -> gtsam.NonlinearFactor:
    """The native GTSAM factor of a spec; ``kernel`` wraps robust (mutual/global) factors."""
    import gtsam

    noise: gtsam.noiseModel.Base = gtsam.noiseModel.Gaussian.Covariance(spec.covariance)
    if spec.robust and kernel != "none":
        # The kernels act on the norm of the whitened 3-vector: leave its 95 % quantile alone.
        k = _KERNEL_WIDTH
        estimator = (
            gtsam.noiseModel.mEstimator.Huber.Create(k)
            if kernel == "huber"
            else gtsam.noiseModel.mEstimator.Cauchy.Create(k)
        )
        noise = gtsam.noiseModel.Robust.Create(estimator, noise)
    pose = gtsam.Pose2(*(float(v) for v in spec.measurement))
    if len(spec.keys) == 1:
        return gtsam.PriorFactorPose2(spec.keys[0], pose, noise)
    return gtsam.BetweenFactorPose2(spec.keys[0], spec.keys[1], pose, noise)


def to_gtsam_graph(
    factors: Iterable[FactorSpec], kernel: RobustKernel = "none"
) -> gtsam.NonlinearFactorGraph:
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    for spec in factors:
        graph.add(to_gtsam_factor(spec, kernel))
    return graph


def to_gtsam_values(poses: Mapping[int, np.ndarray]) -> gtsam.Values:
    import gtsam

    values = gtsam.Values()
    for key, (x, y, yaw) in poses.items():
        values.insert(key, gtsam.Pose2(float(x), float(y), float(yaw)))
    return values
