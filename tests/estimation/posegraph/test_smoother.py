"""Batch and iSAM2 smoothing: same estimate, marginals, GNC against outliers, checkpoints."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from estimation.app.evaluation.metrics import ate
from estimation.errors import EstimationError
from estimation.posegraph import smoother as smoother_module
from estimation.posegraph.events import Localize, Move, Start
from estimation.posegraph.graph import FactorSpec, GraphBuilder, GraphSettings
from estimation.posegraph.keys import pose_key
from estimation.posegraph.marginals import marginal_covariances
from estimation.posegraph.smoother import (
    IncrementalSmoother,
    factor_fingerprint,
    optimize_batch,
    truncated_cost,
)
from estimation.posegraph.synthetic import leapfrog, search_pdf
from sensors.geometry import se2
from tests.paths import REPO


def build(scenario_events: tuple, settings: GraphSettings | None = None) -> GraphBuilder:  # type: ignore[type-arg]
    builder = GraphBuilder(settings)
    builder.add_all(scenario_events)
    return builder


def as_array(estimate: dict[int, np.ndarray], keys: list[int]) -> np.ndarray:
    return np.array([estimate[k] for k in keys])


def assert_same_estimate(a: dict[int, np.ndarray], b: dict[int, np.ndarray]) -> None:
    assert sorted(a) == sorted(b)
    keys = sorted(a)
    diff = as_array(a, keys) - as_array(b, keys)
    assert np.hypot(diff[:, 0], diff[:, 1]).max() < 1e-3  # 1 mm
    assert np.degrees(np.abs(se2.wrap_angle(diff[:, 2]))).max() < 0.01  # 0.01°


@pytest.fixture(scope="module")
def mission():  # type: ignore[no-untyped-def]
    return leapfrog(40, 9, seed=11)


def test_batch_and_isam2_reach_the_same_estimate(mission) -> None:  # type: ignore[no-untyped-def]
    builder = build(mission.events)
    batch = optimize_batch(builder.factors, builder.initial_values(), robust="none")
    smoother = IncrementalSmoother().run(mission.events)
    assert smoother.events == len(mission.events)
    assert len(smoother.update_seconds) == len(mission.events)
    assert_same_estimate(smoother.estimate(), batch.estimate)
    # and both are good: a few centimetres from the truth
    keys = sorted(batch.estimate)
    assert ate(as_array(batch.estimate, keys), mission.truth_array(keys), align=False).rmse_m < 0.1


def test_settled_isam2_reaches_the_batch_optimum_whatever_its_relinearization(
    mission, tmp_path: Path
) -> None:  # type: ignore[no-untyped-def]
    builder = build(mission.events)
    batch = optimize_batch(builder.factors, builder.initial_values(), robust="none")
    keys = sorted(batch.estimate)
    # A coarse threshold leaves linearization points up to 0.1 behind: visibly off the optimum.
    coarse = IncrementalSmoother(relinearize_threshold=0.1, relinearize_skip=3).run(mission.events)
    before = as_array(coarse.estimate(), keys) - as_array(batch.estimate, keys)
    assert np.abs(before[:, :2]).max() > 1e-5
    rounds = coarse.settle()
    assert 2 <= rounds <= 5  # Gauss-Newton from near the optimum: a few steps
    settled = as_array(coarse.estimate(), keys)
    after = settled - as_array(batch.estimate, keys)
    assert np.abs(after[:, :2]).max() < 1e-6
    assert np.abs(se2.wrap_angle(after[:, 2])).max() < 1e-6
    assert coarse.settle() <= 2  # already settled
    assert IncrementalSmoother().settle() == 0  # nothing to settle
    # resumed from a checkpoint (a different relinearization history), settled: the same poses
    half = IncrementalSmoother(relinearize_threshold=0.1, relinearize_skip=3)
    half.run(mission.events[: len(mission.events) // 2], checkpoint=tmp_path / "half.npz")
    resumed = IncrementalSmoother.resume(
        tmp_path / "half.npz", mission.events, relinearize_threshold=0.1, relinearize_skip=3
    )
    resumed.settle()
    assert np.abs(as_array(resumed.estimate(), keys) - settled).max() < 1e-6


def test_gnc_on_clean_data_equals_plain_least_squares(mission) -> None:  # type: ignore[no-untyped-def]
    builder = build(mission.events)
    plain = optimize_batch(builder.factors, builder.initial_values(), robust="none")
    gnc = optimize_batch(builder.factors, builder.initial_values(), robust="gnc_tls")
    assert gnc.outliers == []
    assert_same_estimate(gnc.estimate, plain.estimate)


def test_marginal_covariances_are_consistent() -> None:
    """NEES of every pose of 40 independent small missions (poses within one mission are
    correlated, so many missions make the mean meaningful)."""
    nees = []
    for seed in range(40):
        mission = leapfrog(8, 5, seed=100 + seed)
        builder = build(mission.events)
        batch = optimize_batch(builder.factors, builder.initial_values(), "none", marginals=True)
        assert batch.covariances is not None
        for key, cov in batch.covariances.items():
            err = se2.log(se2.between(batch.estimate[key], mission.truth[key]))  # tangent space
            nees.append(err @ np.linalg.solve(cov, err))
    assert len(nees) == 40 * 48
    assert 2.5 < np.mean(nees) < 3.5
    assert np.mean(np.array(nees) < chi2.ppf(0.95, 3)) == pytest.approx(0.95, abs=0.025)


def test_isam2_marginals_match_batch(mission) -> None:  # type: ignore[no-untyped-def]
    builder = build(mission.events)
    batch = optimize_batch(builder.factors, builder.initial_values(), robust="none", marginals=True)
    assert batch.covariances is not None
    smoother = IncrementalSmoother().run(mission.events)
    for key in list(batch.covariances)[::40]:
        np.testing.assert_allclose(
            smoother.marginal_covariance(key), batch.covariances[key], rtol=0.02, atol=1e-6
        )


def test_marginals_at_the_optimum_equal_the_batch_solvers(mission) -> None:  # type: ignore[no-untyped-def]
    builder = build(mission.events)
    batch = optimize_batch(builder.factors, builder.initial_values(), robust="none", marginals=True)
    assert batch.covariances is not None
    ours = marginal_covariances(builder.factors, batch.estimate)
    assert sorted(ours) == sorted(batch.covariances)
    for key, covariance in ours.items():
        np.testing.assert_allclose(covariance, batch.covariances[key], rtol=1e-6, atol=1e-15)
        np.testing.assert_array_equal(covariance, covariance.T)
    # A pose outside the estimate drops its factors instead of failing.
    gauge = min(batch.estimate)
    assert list(marginal_covariances(builder.factors, {gauge: batch.estimate[gauge]})) == [gauge]


def test_gnc_with_10_percent_gross_outliers_on_2000_poses() -> None:
    """Targets: ATE ≤ 0.10 m and within 10 % of the outlier-free ATE (prediction gate off, so
    that every outlier reaches the graph)."""
    settings = GraphSettings(prediction_gate_probability=None)
    clean = leapfrog(200, 9, seed=5, settings=settings)
    dirty = leapfrog(200, 9, seed=5, settings=settings, outlier_fraction=0.1)
    wrong = len(dirty.outliers)
    assert wrong / (dirty.mutual_events + dirty.global_events) == pytest.approx(0.1, abs=0.02)
    clean_builder, dirty_builder = build(clean.events, settings), build(dirty.events, settings)
    keys = sorted(clean_builder.guesses)
    assert len(keys) == 2000
    truth = clean.truth_array(keys)
    reference = optimize_batch(clean_builder.factors, clean_builder.initial_values(), "none")
    ate_clean = ate(as_array(reference.estimate, keys), truth, align=False).rmse_m
    gnc = optimize_batch(dirty_builder.factors, dirty_builder.initial_values(), "gnc_tls")
    ate_gnc = ate(as_array(gnc.estimate, keys), truth, align=False).rmse_m
    assert ate_gnc <= 0.10
    assert ate_gnc <= 1.10 * ate_clean
    rejected_events = {dirty_builder.factors[i].event for i in gnc.outliers}
    caught = len(rejected_events & dirty.outliers) / wrong
    false = len(rejected_events - dirty.outliers) / (len(dirty_builder.factors) - wrong)
    assert caught >= 0.98  # the few left are the only tie of a pose whose true fix was gated out
    assert false <= 0.005
    # Without robust estimation the same graph is ruined.
    plain = optimize_batch(dirty_builder.factors, dirty_builder.initial_values(), "none")
    assert ate(as_array(plain.estimate, keys), truth, align=False).rmse_m > 0.5


def test_gnc_steps_solved_to_the_default_tolerance_find_what_tight_steps_find(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """GNC's steps only hand the next step a start; the inliers are polished to 1e-10 after."""
    settings = GraphSettings(prediction_gate_probability=None)
    dirty = leapfrog(60, 5, seed=11, settings=settings, outlier_fraction=0.15)
    builder = build(dirty.events, settings)
    loose = optimize_batch(builder.factors, builder.initial_values(), "gnc_tls")
    monkeypatch.setattr(smoother_module, "_GNC_STEP_TOLERANCE", 1e-10)
    tight = optimize_batch(builder.factors, builder.initial_values(), "gnc_tls")
    assert len(tight.outliers) >= 3
    np.testing.assert_array_equal(loose.inliers, tight.inliers)
    assert loose.error == pytest.approx(tight.error, rel=1e-6)
    assert_same_estimate(loose.estimate, tight.estimate)


COALITION = Path(__file__).parent / "data" / "gnc_coalition.npz"


def coalition_graph() -> tuple[list[FactorSpec], dict[int, np.ndarray]]:
    """The last batch graph of generated building 106 (three robots, 358 poses, 1,134 factors,
    seed 106 of the flight in which its own-station scan links were new): its factors and
    initial values."""
    with np.load(COALITION) as data:
        factors = [
            FactorSpec(str(kind), tuple(int(k) for k in keys if k >= 0), m, c, int(event))  # type: ignore[arg-type]
            for kind, keys, m, c, event in zip(
                data["kind"],
                data["keys"],
                data["measurement"],
                data["covariance"],
                data["event"],
                strict=True,
            )
        ]
        initial = {int(k): p for k, p in zip(data["initial_keys"], data["initial"], strict=True)}
    return factors, initial


def test_gnc_keeps_the_inliers_of_least_truncated_cost(monkeypatch: pytest.MonkeyPatch) -> None:
    """Three wrong loop closures that agree with each other (9–17 cm, 1.5–2.2° off) and a wrong
    mutual observation outvote four right factors in one GNC run (truncated cost 329); a
    second run that must keep the four drops the wrong ones instead (293), and wins."""
    factors, initial = coalition_graph()
    cap = chi2.ppf(0.999, 3)
    wrong = {
        ("mutual", (pose_key("b", 49), pose_key("c", 50))),
        ("global", (pose_key("c", 47), pose_key("c", 55))),
        ("global", (pose_key("b", 43), pose_key("c", 74))),
        ("global", (pose_key("b", 43), pose_key("c", 75))),
    }
    result = optimize_batch(factors, initial)
    assert {(factors[i].kind, factors[i].keys) for i in result.outliers} == wrong
    assert truncated_cost(factors, result.estimate, cap) == pytest.approx(293.5, abs=0.5)
    # one run alone keeps the wrong closures
    runs = []
    first_only = smoother_module._gnc

    def once(*args, **kwargs):  # type: ignore[no-untyped-def]
        runs.append(args[3].sum())
        if len(runs) > 1:
            raise AssertionError("a second GNC run")
        return first_only(*args, **kwargs)

    monkeypatch.setattr(smoother_module, "_gnc", once)
    with pytest.raises(AssertionError, match="a second GNC run"):
        optimize_batch(factors, initial)
    monkeypatch.setattr(smoother_module, "_gnc", first_only)
    known = np.array([not f.robust for f in factors])
    graph = smoother_module.to_gtsam_graph(factors, "none")
    values = smoother_module.to_gtsam_values(initial)
    alone, inliers = first_only(factors, graph, values, known, 0.999, 100)
    kept_wrong = {(f.kind, f.keys) for f, ok in zip(factors, inliers, strict=True) if ok} & wrong
    assert kept_wrong == wrong
    assert (~inliers).sum() == 4  # four right factors dropped instead
    cost = truncated_cost(factors, smoother_module.extract_poses(alone), cap)
    assert cost == pytest.approx(328.6, abs=0.5)


def test_settling_can_leave_factors_out(mission) -> None:  # type: ignore[no-untyped-def]
    """The settled estimate without some factors is the batch optimum of the others."""
    builder = build(mission.events)
    smoother = IncrementalSmoother().run(mission.events)
    mutual = [i for i, f in enumerate(builder.factors) if f.kind == "mutual"]
    out = set(mutual[5:8])
    smoother.settle(leave_out=out)
    kept = [f for i, f in enumerate(builder.factors) if i not in out]
    batch = optimize_batch(kept, builder.initial_values(), robust="none")
    keys = sorted(batch.estimate)
    assert np.abs(as_array(smoother.estimate(), keys) - as_array(batch.estimate, keys)).max() < 1e-6
    everything = optimize_batch(builder.factors, builder.initial_values(), robust="none")
    moved = as_array(everything.estimate, keys) - as_array(batch.estimate, keys)
    assert np.abs(moved).max() > 1e-4  # the three factors mattered


def test_batch_refuses_an_unconstrained_robot() -> None:
    builder = GraphBuilder()
    builder.add(Start("a", 0))
    builder.add(Move("a", 1, (1.0, 0.0, 0.0)))
    factors = [f for f in builder.factors if f.kind != "prior"]
    with pytest.raises(EstimationError, match=r"unconstrained: robot a \(2 poses, a0…a1\)"):
        optimize_batch(factors, builder.initial_values())


def test_checkpoint_round_trip_in_process(tmp_path: Path, mission) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "isam.npz"
    half = len(mission.events) // 2
    first = IncrementalSmoother().run(mission.events[:half], checkpoint=path, checkpoint_every=25)
    assert first.events == half
    resumed = IncrementalSmoother.resume(path, mission.events, checkpoint_every=25)
    whole = IncrementalSmoother().run(mission.events)
    assert resumed.events == len(mission.events)
    assert factor_fingerprint(resumed.builder.factors) == factor_fingerprint(whole.builder.factors)
    assert_same_estimate(resumed.estimate(), whole.estimate())


KILLED_RUN = """
import os, signal, sys
from estimation.posegraph.synthetic import leapfrog, search_pdf
from estimation.posegraph.smoother import IncrementalSmoother

events = leapfrog(40, 9, seed=11).events
kill_at = int(sys.argv[2])

def stream():
    for number, event in enumerate(events):
        if number == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)  # dies mid-run, between checkpoints
        yield event

IncrementalSmoother().run(stream(), checkpoint=sys.argv[1], checkpoint_every=25)
"""


def test_a_killed_run_resumes_to_the_same_estimate_without_losing_events(
    tmp_path: Path, mission
) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "isam.npz"
    kill_at = 2 * len(mission.events) // 3 + 7  # not a multiple of the checkpoint period
    proc = subprocess.run(
        [sys.executable, "-c", KILLED_RUN, str(path), str(kill_at)],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    assert proc.returncode == -9, proc.stderr
    with np.load(path) as saved:
        checkpointed = int(saved["events"])
    assert checkpointed == (kill_at // 25) * 25  # the last checkpoint before the kill
    assert not list(tmp_path.glob(".isam.*"))  # no half-written temporary left behind
    resumed = IncrementalSmoother.resume(path, mission.events)
    assert resumed.events == len(mission.events)
    batch = optimize_batch(resumed.builder.factors, resumed.builder.initial_values(), "none")
    assert_same_estimate(resumed.estimate(), batch.estimate)
    whole = IncrementalSmoother().run(mission.events)
    assert factor_fingerprint(resumed.builder.factors) == factor_fingerprint(whole.builder.factors)
    assert_same_estimate(resumed.estimate(), whole.estimate())


def test_checkpoint_errors(tmp_path: Path, mission) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(EstimationError, match=r"missing\.npz: checkpoint not found"):
        IncrementalSmoother.restore(tmp_path / "missing.npz", iter(mission.events))
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(EstimationError, match=r"corrupt\.npz: not a readable checkpoint"):
        IncrementalSmoother.restore(corrupt, iter(mission.events))
    path = tmp_path / "isam.npz"
    IncrementalSmoother().run(mission.events[:100], checkpoint=path)
    with pytest.raises(
        EstimationError, match="checkpoint holds 100 events but the stream has only 50"
    ):
        IncrementalSmoother.restore(path, iter(mission.events[:50]))
    other = leapfrog(40, 9, seed=12).events
    with pytest.raises(EstimationError, match="does not rebuild the checkpointed graph"):
        IncrementalSmoother.restore(path, iter(other))
    with np.load(path) as data:
        entries = {name: data[name] for name in data.files}
    entries["poses"] = np.full_like(entries["poses"], np.nan)
    poisoned = tmp_path / "nan.npz"
    np.savez(poisoned, **entries)
    with pytest.raises(EstimationError, match=r"nan\.npz: checkpoint holds non-finite poses"):
        IncrementalSmoother.restore(poisoned, iter(mission.events))


def test_isam2_reports_an_update_that_fails_with_qr_too(monkeypatch: pytest.MonkeyPatch) -> None:
    import gtsam

    made: list[str] = []  # the factorization of each iSAM2 the smoother starts

    class Failing:
        def __init__(self, params: gtsam.ISAM2Params | None = None) -> None:
            made.append("given" if params is None else str(params.getFactorization()))

        def update(self, *args: object) -> None:
            raise RuntimeError("Indeterminate linear system detected")

        def calculateBestEstimate(self) -> None:
            raise RuntimeError("no estimate")

    smoother = IncrementalSmoother()
    smoother.add(Start("a", 0))
    smoother.isam = Failing()
    monkeypatch.setattr(gtsam, "ISAM2", Failing)
    with pytest.raises(EstimationError, match=r"iSAM2 update at event 1 failed: Indeterminate "
                                              r"linear system detected; with QR too"):  # fmt: skip
        smoother.add(Move("a", 1, (1.0, 0.0, 0.0)))
    assert smoother.refactorized == "event 1"
    assert made == ["given", "QR"]  # the restart asked for QR


def test_huber_and_cauchy_kernels_soften_a_wrong_loop_closure(mission) -> None:  # type: ignore[no-untyped-def]
    """M-estimators: weaker than GNC, but they cut a gross outlier's pull; iSAM2 applies them
    too (it re-weights only where it relinearizes, so it lands close to, not on, the batch)."""
    truth = mission.truth
    wrong = se2.between(truth[pose_key("a", 5)], truth[pose_key("a", 30)]) + np.array(
        [3.0, 2.0, 0.5]
    )
    events = (*mission.events, Localize("a", 30, search_pdf(wrong, 0.05, 0.02), ("a", 5)))
    builder = build(events)
    keys = sorted(builder.guesses)
    reference = mission.truth_array(keys)

    def error(estimate: dict[int, np.ndarray]) -> float:
        return ate(as_array(estimate, keys), reference, align=False).rmse_m

    plain = error(optimize_batch(builder.factors, builder.initial_values(), "none").estimate)
    for kernel in ("huber", "cauchy"):
        batch = optimize_batch(builder.factors, builder.initial_values(), robust=kernel)  # type: ignore[arg-type]
        assert error(batch.estimate) < 0.7 * plain
        smoother = IncrementalSmoother(kernel=kernel).run(events)  # type: ignore[arg-type]
        diff = as_array(smoother.estimate(), keys) - as_array(batch.estimate, keys)
        assert np.hypot(diff[:, 0], diff[:, 1]).max() < 0.05


def test_relative_covariance_equals_the_composed_odometry() -> None:
    from estimation.posegraph.graph import FactorSpec
    from estimation.posegraph.marginals import relative_covariances

    step_a, step_b = np.array([1.0, 0.5, 0.4]), np.array([1.0, -0.2, 0.3])
    q = np.diag([0.01, 0.02, 0.003])
    factors = [
        FactorSpec("prior", (1,), np.zeros(3), np.eye(3) * 1e-12, 0),
        FactorSpec("odometry", (1, 2), step_a, q, 1),
        FactorSpec("odometry", (2, 3), step_b, q, 2),
    ]
    estimate = {1: np.zeros(3), 2: step_a, 3: se2.compose(step_a, step_b)}
    relative = relative_covariances(factors, estimate)
    pose, expected = se2.propagate_compose(np.zeros(3), np.zeros((3, 3)), step_a, q)
    pose, expected = se2.propagate_compose(pose, expected, step_b, q)
    np.testing.assert_allclose(relative(1, 3), expected, atol=1e-9)
    np.testing.assert_allclose(relative(2, 3), q, atol=1e-9)  # one step, whatever came before
    # A loop closure shrinks the uncertainty between its ends below the chain's.
    closed = [*factors, FactorSpec("global", (1, 3), estimate[3], q, 3)]
    assert np.linalg.det(relative_covariances(closed, estimate)(1, 3)) < np.linalg.det(expected)


def test_an_update_cholesky_declares_indeterminate_goes_on_with_qr() -> None:
    """A factor a thousand times tighter than its neighbours (a registration's floor gone
    wrong, say): Cholesky declares the system indeterminate, QR copes, from then on."""
    tight = np.diag([1e-12, 1e-12, 1e-12])
    events = [Start("a", 0), *(Move("a", k, (1.0, 0.0, 0.1)) for k in range(1, 5))]
    step = np.array([1.0, 0.0, 0.1])
    events.append(Localize("a", 3, search_pdf(step, 0.05, 0.02), ("a", 2), pose=tuple(step),
                           covariance=tuple(map(tuple, tight))))  # fmt: skip
    loop = np.array([4.0, 0.5, 0.4])
    events.append(Localize("a", 4, search_pdf(loop, 0.05, 0.02), ("a", 0), pose=tuple(loop),
                           covariance=tuple(map(tuple, tight * 1e-6))))  # fmt: skip
    smoother = IncrementalSmoother()
    for event in events:
        smoother.add(event)
    assert smoother.refactorized is not None
    estimate = smoother.estimate()
    np.testing.assert_allclose(estimate[pose_key("a", 4)], loop, atol=1e-6)
    a2, a3 = estimate[pose_key("a", 2)], estimate[pose_key("a", 3)]
    np.testing.assert_allclose(se2.between(a2, a3), step, atol=1e-5)
    # It goes on with QR: more events, and the checkpoint state, work as before.
    smoother.add(Move("a", 5, (1.0, 0.0, 0.0)))
    assert pose_key("a", 5) in smoother.estimate()
    assert smoother.refactorized == "event 5"  # the first tight factor
