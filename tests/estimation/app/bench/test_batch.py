"""``coopmap bench batch``: fresh ``coopmap batch`` processes timed from the outside."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from estimation.app.bench.batch import format_batch_report, run_batch_benchmark
from estimation.errors import EstimationError
from tests.estimation.app.cli.clirun import assert_one_line_error, run
from tests.estimation.app.missions import ONE_STEP_MISSION


@pytest.fixture(scope="module")
def measured(tmp_path_factory: pytest.TempPathFactory) -> dict:
    from estimation.app.sim.simulate import run_simulation

    root = tmp_path_factory.mktemp("bench_batch")
    (root / "small.yaml").write_text(ONE_STEP_MISSION)
    dataset = root / "small"
    run_simulation(root / "small.yaml", dataset)
    before = sorted(p.relative_to(dataset) for p in dataset.rglob("*"))
    result = run_batch_benchmark(dataset, repeats=1, warm_up=False)
    # The dataset is only read: its results went to a temporary folder.
    assert sorted(p.relative_to(dataset) for p in dataset.rglob("*")) == before
    return result


def test_each_run_is_a_process_measured_from_the_outside(measured: dict) -> None:
    runs = measured["runs"]
    assert [r["figures"] for r in runs] == [True, False]
    for r in runs:
        assert set(r["steps_s"]) == {"decode", "sweeps_and_beacons", "optimize", "search",
                                     "fusion"}  # fmt: skip
        steps = sum(r["steps_s"].values())
        # The process's wall time holds its steps, and starting and importing besides.
        assert r["wall_s"] > steps + 0.2
        assert r["outside_steps_s"] == pytest.approx(r["wall_s"] - steps)
        assert r["cpu_s"] > 0.5 * steps
        # A process that imported numpy, numba and gtsam is well over 100 MB.
        assert 100 < r["peak_rss_mb"] < 24_000
    assert measured["sweeps"] == runs[0]["sweeps"] > 0
    assert measured["telegrams"] > 1000
    # Drawing the figures is the difference between the two runs' time outside the steps.
    assert runs[0]["outside_steps_s"] > runs[1]["outside_steps_s"]
    for key in ("with_figures", "without_figures"):
        s = measured[key]
        assert s["wall_min_s"] <= s["wall_s"] <= s["wall_max_s"]
        assert s["met"] == (s["wall_s"] <= 4.0 and s["peak_rss_mb"] <= 400.0)


def test_the_report_names_both_ways_and_the_target(measured: dict) -> None:
    text = format_batch_report(measured)
    assert text.startswith("bench batch: coopmap batch on ")
    assert "1 run each way, alternating\n" in text  # no warm-up run was asked for
    assert "  with figures: wall " in text
    assert "  --no-figures: wall " in text
    assert "target ≤ 4 s and ≤ 400 MB per run" in text
    assert json.loads(json.dumps(measured)) == measured


def test_a_missing_dataset_or_a_failing_batch_is_one_line(tmp_path: Path) -> None:
    code, out, err = run("bench", "batch", "--dataset", tmp_path / "nothing", "--repeats", "1")
    assert_one_line_error(code, out, err, r"bench batch: .*nothing: no such dataset folder")
    empty = tmp_path / "empty"
    empty.mkdir()
    code, out, err = run("bench", "batch", "--dataset", empty, "--repeats", "1")
    assert_one_line_error(code, out, err, r"bench batch: coopmap batch failed \(2\): coopmap: "
                                          r"error: .*empty")  # fmt: skip
    with pytest.raises(EstimationError, match="repeats must be at least 1"):
        run_batch_benchmark(empty, repeats=0)


def _children() -> set[int]:
    """This process's child processes (Linux)."""
    found: set[int] = set()
    for task in Path(f"/proc/{os.getpid()}/task").iterdir():
        found |= {int(pid) for pid in (task / "children").read_text().split()}
    return found


def test_a_run_past_its_time_is_killed_and_reaped(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import estimation.app.bench.batch as bench

    before = _children()
    monkeypatch.setattr(bench, "RUN_TIMEOUT_S", 0.05)
    folder = tmp_path / "some"
    folder.mkdir()
    with pytest.raises(EstimationError, match=r"a run took longer than 0 s"):
        run_batch_benchmark(folder, repeats=1, warm_up=False)
    assert _children() == before


def test_ctrl_c_while_a_run_is_timed_leaves_no_batch_running(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import estimation.app.bench.batch as bench

    before = _children()

    def interrupted(_: float) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(bench.time, "sleep", interrupted)
    folder = tmp_path / "some"
    folder.mkdir()
    with pytest.raises(KeyboardInterrupt):
        run_batch_benchmark(folder, repeats=1, warm_up=False)
    assert _children() == before
