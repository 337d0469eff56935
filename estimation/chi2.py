"""Quantiles of the chi-square distribution, the gates and kernel widths of the pose graph.

``scipy.stats`` costs about 0.6 s to import, and every command that builds a pose graph would pay
it for a handful of constants. The chi-square quantile has a closed form in the inverse regularized
lower incomplete gamma function, which ``scipy.special`` (loaded anyway by ``scipy.linalg``)
provides: ``chi2.ppf(p, k) == 2 * gammaincinv(k / 2, p)``, the very expression ``scipy.stats``
evaluates, so the values are bit-identical.
"""

from __future__ import annotations

import math

from scipy.special import gammainc, gammaincinv

__all__ = ["chi2_cdf", "chi2_quantile"]


def chi2_quantile(probability: float, dof: int) -> float:
    """The value a chi-square variable with ``dof`` degrees of freedom stays below with probability.

    Same as ``scipy.stats.chi2.ppf(probability, dof)``: 0 at probability 0, infinity at 1, NaN
    outside [0, 1].
    """
    return float(2.0 * gammaincinv(0.5 * dof, probability))


def chi2_cdf(value: float, dof: int) -> float:
    """The probability that a chi-square variable with ``dof`` degrees of freedom stays below
    ``value`` (``scipy.stats.chi2.cdf``): 0 at or below 0, 1 at infinity, NaN for NaN."""
    return float(gammainc(0.5 * dof, max(value, 0.0) * 0.5)) if value == value else math.nan
