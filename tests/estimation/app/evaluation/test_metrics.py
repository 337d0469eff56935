"""ATE, RPE and the Kümmerle relations metric, against evo and the published Intel figures."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimation.app.evaluation.metrics import align_se2, associate, ate, relations_error, rpe
from estimation.errors import EstimationError
from sensors.geometry import se2
from sensors.trajio import read_carmen_odometry, read_relations
from tests.paths import DATA

INTEL_LOG = DATA / "carmen_corrected" / "intel-corrected.log.gz"
INTEL_RELATIONS = DATA / "slam_benchmark_relations" / "intel.relations"
#: The offset from the corrected log's stamps to the relations' (data README).
INTEL_OFFSET_S = 976052857.3373


def wander(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    steps = np.column_stack([rng.uniform(0.1, 0.5, n), np.zeros(n), rng.normal(0, 0.2, n)])
    poses = [np.zeros(3)]
    for step in steps[1:]:
        poses.append(se2.compose(poses[-1], step))
    return np.array(poses)


def test_ate_is_zero_after_aligning_a_rigidly_moved_copy() -> None:
    reference = wander(200, 0)
    T = np.array([3.0, -2.0, 1.1])
    moved = se2.compose(T, reference)
    result = ate(moved, reference)
    assert result.rmse_m < 1e-9
    assert result.rmse_rad < 1e-9
    np.testing.assert_allclose(result.alignment, se2.inverse(T), atol=1e-9)
    unaligned = ate(moved, reference, align=False)
    assert unaligned.rmse_m > 1.0


def test_ate_without_alignment_measures_a_known_offset() -> None:
    reference = wander(100, 1)
    shifted = reference + np.array([0.3, -0.4, 0.05])
    result = ate(shifted, reference, align=False)
    assert result.rmse_m == pytest.approx(0.5)
    assert result.rmse_deg == pytest.approx(math.degrees(0.05))
    assert result.max_m == pytest.approx(0.5)


def test_ate_matches_evo() -> None:
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    reference = wander(300, 2)
    rng = np.random.default_rng(3)
    estimate = se2.compose(np.array([1.0, 2.0, 0.4]), reference)
    estimate[:, :2] += rng.normal(0, 0.05, (300, 2))
    estimate[:, 2] += rng.normal(0, 0.01, 300)

    def traj(poses: np.ndarray) -> PoseTrajectory3D:
        xyz = np.column_stack([poses[:, :2], np.zeros(len(poses))])
        quat = np.column_stack(
            [np.cos(poses[:, 2] / 2), np.zeros((len(poses), 2)), np.sin(poses[:, 2] / 2)]
        )
        return PoseTrajectory3D(xyz, quat, np.arange(len(poses), dtype=float))

    ref_t, est_t = sync.associate_trajectories(traj(reference), traj(estimate))
    est_t.align(ref_t, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref_t, est_t))
    ours = ate(estimate, reference)
    assert ours.rmse_m == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)
    assert 0.05 < ours.rmse_m < 0.1


def test_rpe_of_a_constant_bias_per_step() -> None:
    reference = wander(50, 4)
    steps = se2.between(reference[:-1], reference[1:])
    biased = [reference[0]]
    for step in steps:
        biased.append(se2.compose(biased[-1], se2.compose(step, np.array([0.01, 0.0, 0.002]))))
    result = rpe(np.array(biased), reference)
    assert result.rmse_m == pytest.approx(0.01, rel=1e-6)
    assert result.rmse_rad == pytest.approx(0.002, rel=1e-6)
    assert result.count == 49
    assert rpe(reference, reference, delta=5).rmse_m < 1e-12


def test_alignment_of_a_single_pose_uses_its_heading() -> None:
    T = align_se2(np.array([[0.0, 0.0, 0.0]]), np.array([[1.0, 1.0, 0.5]]))
    np.testing.assert_allclose(T, [1.0, 1.0, 0.5])


def test_associate_picks_nearest_stamp_within_tolerance_first_row_on_ties() -> None:
    stamps = np.array([1.0, 2.0, 2.0, 3.0, 0.5])
    index = associate(stamps, np.array([2.001, 0.6, 9.0, 2.999]), max_dt_s=0.2)
    np.testing.assert_array_equal(index, [1, 4, -1, 3])


@pytest.mark.parametrize(
    ("call", "pattern"),
    [
        (
            lambda: ate(np.zeros((3, 3)), np.zeros((4, 3))),
            "estimate has 3 poses but reference has 4",
        ),
        (lambda: ate(np.zeros((3, 2)), np.zeros((3, 2))), r"need an \(N, 3\) array"),
        (lambda: ate(np.full((2, 3), np.nan), np.zeros((2, 3))), "estimate: poses hold NaN or inf"),
        (lambda: ate(np.zeros((0, 3)), np.zeros((0, 3))), "no poses to compare"),
        (
            lambda: rpe(np.zeros((3, 3)), np.zeros((3, 3)), delta=3),
            r"RPE delta must be in \[1, 2\], got 3",
        ),
        (lambda: associate(np.array([]), np.array([1.0]), 0.1), "non-empty 1-D array of stamps"),
        (
            lambda: relations_error(
                np.array([0.0]), np.zeros((1, 3)), np.array([[5.0, 6.0]]), np.zeros((1, 3))
            ),
            "no relation matches the trajectory's stamps",
        ),
    ],
)
def test_metric_errors_name_the_problem(call, pattern: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(EstimationError, match=pattern):
        call()


def test_relations_metric_on_a_synthetic_trajectory() -> None:
    reference = wander(100, 5)
    stamps = np.arange(100, dtype=float)
    pairs = np.array([[i, i + 7] for i in range(0, 90, 3)], dtype=float)
    truth = se2.between(reference[pairs[:, 0].astype(int)], reference[pairs[:, 1].astype(int)])
    result = relations_error(stamps, reference, pairs, truth)
    assert result.trans_mean_m < 1e-12
    assert result.count == 30
    off = relations_error(stamps, reference, pairs, se2.compose(truth, np.array([0.1, 0.0, 0.0])))
    assert off.trans_mean_m == pytest.approx(0.1)
    assert off.trans_std_m == pytest.approx(0.0, abs=1e-12)


@pytest.mark.skipif(
    not (INTEL_LOG.exists() and INTEL_RELATIONS.exists()), reason="../shared/data is not available"
)
def test_corrected_intel_log_scores_the_published_relations_error() -> None:
    """Kümmerle et al. 2009 relations vs the Freiburg corrected Intel log (Hähnel's data):
    0.068 ± 0.070 m and 2.4 ± 2.9° (data README)."""
    stamps, poses = read_carmen_odometry(INTEL_LOG)
    relation_stamps, relations = read_relations(INTEL_RELATIONS)
    result = relations_error(
        stamps, poses, relation_stamps, relations, max_dt_s=0.005, time_offset_s=INTEL_OFFSET_S
    )
    assert result.unmatched == 0
    assert result.count == 2984
    assert result.trans_mean_m == pytest.approx(0.068, abs=0.0005)
    assert result.trans_std_m == pytest.approx(0.070, abs=0.0005)
    assert result.rot_mean_deg == pytest.approx(2.4, abs=0.05)
    assert result.rot_std_deg == pytest.approx(2.9, abs=0.05)
