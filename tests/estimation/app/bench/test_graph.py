"""The graph benchmark: the iSAM2 target on leapfrog_5000, the real graphs, the command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from estimation.app.bench.graph import leapfrog_5000, pose_difference, run_g2o_case
from estimation.app.cli.main import app
from estimation.app.resources import DATA_DIR
from estimation.posegraph.smoother import IncrementalSmoother
from sensors.geometry import se2

INTEL = DATA_DIR / "pose_graphs_g2o" / "intel.g2o"


def test_isam2_work_per_event_is_flat_on_leapfrog_5000() -> None:
    """Issue 18's per-event target is a time (p99 < 5 ms), measured by ``coopmap bench graph``;
    a timed assertion here would measure the machine's load. What the test holds fixed is the
    work behind that time: the variables iSAM2 eliminates again per event stay few (a p99 of 70
    of 5,000 when written) and do not grow as the mission does."""
    scenario = leapfrog_5000()
    assert len(scenario.truth) == 5000
    smoother = IncrementalSmoother().run(scenario.events)
    work = np.array(smoother.reeliminated)
    assert len(work) == len(smoother.update_cpu_seconds) == len(scenario.events) > 10_000
    assert np.percentile(work, 50) <= 10
    assert np.percentile(work, 99) <= 100
    half = len(work) // 2
    assert np.percentile(work[half:], 99) <= 1.2 * np.percentile(work[:half], 99)
    assert len(smoother.estimate()) == 5000


@pytest.mark.skipif(not INTEL.exists(), reason="../shared/data is not available")
def test_intel_graph_batch_and_isam2_agree() -> None:
    result = run_g2o_case("intel", INTEL)
    assert result.poses == 1728
    assert result.events == 1728
    assert result.batch_error < 25.0  # from 277 at the file's initial values
    assert result.isam2_error == pytest.approx(result.batch_error, rel=1e-3)
    assert result.max_difference_mm < 3.0
    assert result.aligned_difference_mm <= result.max_difference_mm + 1e-9
    assert result.ratio > 1.0


@pytest.mark.skipif(not INTEL.exists(), reason="../shared/data is not available")
def test_bench_graph_command_prints_json() -> None:
    result = CliRunner().invoke(app, ["bench", "graph", "--json", "--case", "intel"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["benchmark"] == "graph"
    assert [c["name"] for c in report["cases"]] == ["intel"]
    for key in ("batch_seconds", "isam2_update_median_ms", "isam2_update_p99_ms", "poses", "ratio"):
        assert report[key] == report["cases"][0][key]
    assert report["poses"] == 1728
    case = report["cases"][0]
    assert 0 <= case["reeliminated_median"] <= case["reeliminated_p99"] <= 1728


@pytest.mark.parametrize(
    ("args", "pattern"),
    [
        (["--case", "nope"], "unknown graph bench case 'nope'"),
        (["--case", "intel", "--data", "{tmp}"], r"no graph bench case could run"),
    ],
)
def test_bench_graph_errors_are_one_line(tmp_path: Path, args: list[str], pattern: str) -> None:
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    result = CliRunner().invoke(app, ["bench", "graph", *args])
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1
    import re

    assert re.search(pattern, lines[0]), lines[0]


def test_the_difference_is_reported_raw_and_with_the_gauge_aligned() -> None:
    """Two estimates of one graph in gauges a known SE(2) transform apart (plus millimetres of
    disagreement): raw, they differ by the transform; aligned, by the disagreement alone."""
    rng = np.random.default_rng(3)
    batch = {k: np.array([x, y, yaw]) for k, (x, y, yaw) in enumerate(
        np.column_stack([rng.uniform(-20, 20, (60, 2)), rng.uniform(-3, 3, 60)]))}  # fmt: skip
    T = np.array([12.0, -9.0, np.radians(1.46)])  # the other gauge: 15 m, 1.46°
    wiggle = {k: np.array([rng.normal(0, 1e-3), rng.normal(0, 1e-3), rng.normal(0, 1e-4)])
              for k in batch}  # fmt: skip
    isam2 = {k: se2.compose(se2.inverse(T), p + wiggle[k]) for k, p in batch.items()}
    d = pose_difference(batch, isam2)
    assert d.gauge_m == pytest.approx(15.0, abs=0.01)
    assert d.gauge_deg == pytest.approx(1.46, abs=0.01)
    assert d.raw_mm > 15_000
    assert d.raw_deg == pytest.approx(1.46, abs=0.05)
    largest = max(np.hypot(*w[:2]) for w in wiggle.values()) * 1e3
    assert d.aligned_mm < 2 * largest + 1.0
    assert d.aligned_mm > 0.2 * largest
    assert d.aligned_deg < 0.05
    same = pose_difference(batch, batch)
    assert (same.raw_mm, same.aligned_mm, same.gauge_m) == (0.0, 0.0, 0.0)
