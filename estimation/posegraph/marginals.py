"""Marginal covariances of the pose graph: of each pose, and of poses relative to each other
(joint marginals), in gtsam's tangent space; without robust kernels, linearized at an estimate.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import gtsam
import numpy as np

from estimation.errors import EstimationError
from estimation.posegraph.graph import FactorSpec
from estimation.posegraph.gtsam_factors import to_gtsam_graph, to_gtsam_values
from sensors.geometry import se2

__all__ = ["RelativeCovariances", "marginal_covariances", "relative_covariances"]


def marginal_covariances(
    factors: Sequence[FactorSpec], estimate: Mapping[int, np.ndarray]
) -> dict[int, np.ndarray]:
    """The 3×3 marginal covariance of every pose of ``estimate`` in the graph of ``factors``
    (without robust kernels) linearized at ``estimate``, in gtsam's tangent space of the pose:
    (x_m, y_m) along the pose's own axes, then yaw_rad. Factors on poses outside ``estimate``
    are left out."""
    kept = [f for f in factors if all(k in estimate for k in f.keys)]
    try:
        marginals = gtsam.Marginals(to_gtsam_graph(kept), to_gtsam_values(estimate))
        out = {k: np.asarray(marginals.marginalCovariance(k)) for k in estimate}
    except RuntimeError as exc:
        raise EstimationError(f"marginal covariances failed: {exc}") from exc
    return {k: 0.5 * (c + c.T) for k, c in out.items()}


class RelativeCovariances:
    """The covariances of relative poses T_a_b = a⁻¹·b (in the tangent space at T_a_b, as a
    between-factor's) from joint marginals of the graph of ``factors`` at ``estimate``; factors
    on poses outside ``estimate`` are left out. Call it with (a, b) for one; :meth:`around`
    gives many relative to one pose from a single joint marginal."""

    def __init__(self, factors: Sequence[FactorSpec], estimate: Mapping[int, np.ndarray]) -> None:
        kept = [f for f in factors if all(k in estimate for k in f.keys)]
        try:
            self._marginals = gtsam.Marginals(to_gtsam_graph(kept), to_gtsam_values(estimate))
        except RuntimeError as exc:
            raise EstimationError(f"marginal covariances failed: {exc}") from exc
        self._estimate = estimate

    def _relative(self, a: int, b: int, joint: np.ndarray) -> np.ndarray:
        """The covariance of T_a_b from the 6×6 joint marginal of a and b."""
        # a·Exp(δa) and b·Exp(δb) give T_a_b·Exp(−Ad(T_a_b⁻¹)·δa + δb) to first order.
        T_a_b = se2.between(self._estimate[a], self._estimate[b])
        H = np.hstack([-se2.adjoint(se2.inverse(T_a_b)), np.eye(3)])
        out = H @ joint @ H.T
        return np.asarray(0.5 * (out + out.T))

    def __call__(self, a: int, b: int) -> np.ndarray:
        joint = self._marginals.jointMarginalCovariance(gtsam.KeyVector([a, b]))
        full = np.block([[joint.at(a, a), joint.at(a, b)], [joint.at(b, a), joint.at(b, b)]])
        return self._relative(a, b, full)

    def around(self, a: int, keys: Sequence[int]) -> list[np.ndarray]:
        """The covariances of T_a_k for each of ``keys`` (a itself gives zeros), from one joint
        marginal of a and all of them: a hundred keys in the time of a few pairs."""
        others = list(dict.fromkeys(k for k in keys if k != a))
        if not others:
            return [np.zeros((3, 3)) for _ in keys]
        joint = self._marginals.jointMarginalCovariance(gtsam.KeyVector([a, *others]))
        aa = joint.at(a, a)
        out = {a: np.zeros((3, 3))}
        for k in others:
            full = np.block([[aa, joint.at(a, k)], [joint.at(k, a), joint.at(k, k)]])
            out[k] = self._relative(a, k, full)
        return [out[k] for k in keys]


def relative_covariances(
    factors: Sequence[FactorSpec], estimate: Mapping[int, np.ndarray]
) -> RelativeCovariances:
    """The covariances of relative poses in the graph of ``factors`` at ``estimate``
    (:class:`RelativeCovariances`; call it with (a, b))."""
    return RelativeCovariances(factors, estimate)
