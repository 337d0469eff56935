"""The Bayesian cell update of the paper's eq. 3 and its log-odds form.

For a cell with prior probability of occupancy ``p`` and a measurement that says "occupied" with
probability ``e``, the paper's eq. 3 gives the posterior

    P = (1 + (1 − e)(1 − p) / (e · p))⁻¹

which is the same as adding log-odds, ``l(P) = l(p) + l(e)`` with ``l(x) = ln(x / (1 − x))``
(the prior of every cell is 0.5, whose log-odds is 0). The grid stores log-odds: an update is
one addition, and two maps merge by adding their cells.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["bayes_update", "logodds", "probability"]


def logodds(probability: ArrayLike) -> np.ndarray:
    """ln(p / (1 − p)) of probabilities in (0, 1)."""
    p = np.asarray(probability, dtype=np.float64)
    return np.asarray(np.log(p) - np.log1p(-p))


def probability(logodds: ArrayLike) -> np.ndarray:
    """The probability whose log-odds is ``logodds`` (the logistic function)."""
    lo = np.asarray(logodds, dtype=np.float64)
    return np.asarray(0.5 * (1.0 + np.tanh(0.5 * lo)))


def bayes_update(prior: ArrayLike, evidence: ArrayLike) -> np.ndarray:
    """Posterior occupancy from a prior ``p`` and a measurement's ``e`` (paper eq. 3)."""
    p = np.asarray(prior, dtype=np.float64)
    e = np.asarray(evidence, dtype=np.float64)
    return np.asarray(1.0 / (1.0 + (1.0 - e) * (1.0 - p) / (e * p)))
