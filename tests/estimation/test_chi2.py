"""Chi-square quantiles without ``scipy.stats``, and no batch module importing it."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest
from scipy.stats import chi2

from estimation.chi2 import chi2_cdf, chi2_quantile

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("dof", [1, 2, 3, 6])
@pytest.mark.parametrize("probability", [0.025, 0.5, 0.9, 0.95, 0.975, 0.99, 0.999])
def test_quantile_equals_scipy_stats_bit_for_bit(probability: float, dof: int) -> None:
    assert chi2_quantile(probability, dof) == float(chi2.ppf(probability, dof))


def test_quantile_at_the_ends_and_outside() -> None:
    assert chi2_quantile(0.0, 3) == 0.0
    assert chi2_quantile(1.0, 3) == math.inf
    assert math.isnan(chi2_quantile(1.5, 3))
    # 2 dof: the exponential with mean 2, whose quantile is -2 ln(1 - p)
    assert chi2_quantile(0.95, 2) == pytest.approx(-2.0 * math.log(0.05), rel=1e-14)


def test_batch_modules_do_not_import_scipy_stats_nor_the_mission_simulator() -> None:
    """``scipy.stats`` costs ~0.6 s to import, the mission simulator with its planner ~0.1 s;
    nothing ``coopmap batch`` loads may pull them in."""
    code = (
        "import sys\n"
        "import estimation.app.cli.main, estimation.app.cli.mission\n"
        "import estimation.app.pipeline, estimation.app.results, estimation.app.figures\n"
        "import estimation.posegraph.validate, estimation.search.stations\n"
        "print('scipy.stats' in sys.modules, 'sensors.sim.mission' in sys.modules,\n"
        "      'estimation.posegraph.graph' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True
    )
    assert out.stdout.split() == ["False", "False", "True"]


@pytest.mark.parametrize("dof", [1, 3, 6])
@pytest.mark.parametrize("value", [0.0, 0.1, 1.0, 7.8, 11.3, 36.0])
def test_cdf_equals_scipy_stats(value: float, dof: int) -> None:
    assert chi2_cdf(value, dof) == pytest.approx(float(chi2.cdf(value, dof)), rel=1e-14, abs=1e-300)


def test_cdf_at_the_ends_and_of_nan() -> None:
    assert chi2_cdf(-1.0, 3) == 0.0
    assert chi2_cdf(math.inf, 3) == 1.0
    assert math.isnan(chi2_cdf(math.nan, 3))
    assert chi2_cdf(chi2_quantile(0.99, 3), 3) == pytest.approx(0.99, abs=1e-12)
