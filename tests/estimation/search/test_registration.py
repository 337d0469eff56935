"""Planar point-to-plane registration of station clouds (estimation/search/registration.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimation.errors import EstimationError
from estimation.posegraph.events import checked_covariance
from estimation.search import registration
from estimation.search.normals import jacobi3 as _jacobi3
from estimation.search.registration import (
    Cloud,
    RegistrationParams,
    _gauss_newton,
    _moved,
    _Near,
    _normals,
    register,
)
from sensors.geometry import se2

PARAMS = RegistrationParams()


def _room(rng: np.random.Generator, corridor: bool = False) -> np.ndarray:
    """Points on the walls of a 6 m × 4 m room (or a 30 m × 2 m corridor without end walls)
    and on a pillar, 0.2–2.5 m high."""
    h = rng.uniform(0.2, 2.5, 4000)
    t = rng.uniform(0, 1, 4000)
    if corridor:
        x0, x1, y0, y1 = -15.0, 15.0, -1.0, 1.0
        walls = [np.c_[x0 + (x1 - x0) * t[:2000], np.full(2000, y0), h[:2000]],
                 np.c_[x0 + (x1 - x0) * t[2000:], np.full(2000, y1), h[2000:]]]  # fmt: skip
        return np.vstack(walls) + rng.normal(0, 0.003, (4000, 3))
    x0, x1, y0, y1 = -3.0, 3.0, -2.0, 2.0
    q = np.array_split(np.arange(4000), 5)
    walls = [np.c_[x0 + 6 * t[q[0]], np.full(len(q[0]), y0), h[q[0]]],
             np.c_[x0 + 6 * t[q[1]], np.full(len(q[1]), y1), h[q[1]]],
             np.c_[np.full(len(q[2]), x0), y0 + 4 * t[q[2]], h[q[2]]],
             np.c_[np.full(len(q[3]), x1), y0 + 4 * t[q[3]], h[q[3]]]]  # fmt: skip
    a = 2 * math.pi * t[q[4]]
    walls.append(np.c_[1.0 + 0.2 * np.cos(a), 0.5 + 0.2 * np.sin(a), h[q[4]]])
    return np.vstack(walls) + rng.normal(0, 0.003, (4000, 3))


def _seen_from(points_map: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """The map points in the robot frame of ``pose``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d = points_map[:, :2] - pose[:2]
    return np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], points_map[:, 2]]


def test_registration_recovers_the_relative_pose_from_a_seed_decimetres_off() -> None:
    rng = np.random.default_rng(1)
    a, b = np.array([0.3, -0.2, 0.1]), np.array([-0.8, 0.6, 0.9])
    target = Cloud.of(_seen_from(_room(rng), a), PARAMS)
    source = Cloud.of(_seen_from(_room(rng), b), PARAMS)
    truth = se2.between(a, b)
    found = register(source, target, truth + np.array([0.25, -0.2, math.radians(4.0)]), PARAMS)
    assert found is not None
    assert found.accepted(PARAMS)
    assert math.dist(found.pose[:2], truth[:2]) < 0.005
    assert abs(math.remainder(found.pose[2] - truth[2], 2 * math.pi)) < math.radians(0.1)
    assert found.inliers > 0.85
    assert found.rms_m < 0.01
    seed = truth + np.array([0.25, -0.2, math.radians(4.0)])
    assert found.moved_m == pytest.approx(math.dist(found.pose[:2], seed[:2]))
    sigmas = np.sqrt(np.diag(found.covariance))
    assert sigmas[0] >= PARAMS.min_sigma_m * 0.999
    assert sigmas[2] >= PARAMS.min_sigma_rad * 0.999
    checked_covariance(found.covariance, "registration")  # symmetric positive definite


def test_a_corridor_is_uncertain_along_its_axis_and_a_prior_holds_the_seed_there() -> None:
    rng = np.random.default_rng(2)
    target = Cloud.of(_room(rng, corridor=True), PARAMS)
    source = Cloud.of(_room(rng, corridor=True), PARAMS)
    seed = np.array([0.1, 0.03, 0.0])
    free = register(source, target, seed, PARAMS)
    assert free is not None
    sx, sy = np.sqrt(np.diag(free.covariance))[:2]
    assert sx > 5 * sy  # along the axis the points say little
    assert sx > 0.05  # the cost profiled along it is near flat (0.08-0.30 over three seeds)
    assert abs(free.pose[1]) < 0.005  # across it they fix the pose
    held = register(source, target, seed, PARAMS, prior=np.diag([0.02, 0.02, 0.005]) ** 2)
    assert held is not None
    assert abs(held.pose[0] - seed[0]) < 0.01
    assert abs(held.pose[1]) < 0.01  # the prior 3 cm off moves it by 7 mm
    assert np.sqrt(held.covariance[0, 0]) <= 0.0201


def test_a_corridor_registration_that_only_creeps_along_the_axis_has_converged() -> None:
    """Along a corridor without features the pose creeps along the axis for every iteration
    there is: settled across it and in yaw, the registration has converged (its heading is what
    a link across an untied turn needs), and says it measured nothing along the axis."""
    rng = np.random.default_rng(5)
    target = Cloud.of(_room(rng, corridor=True), PARAMS)
    source = Cloud.of(_room(rng, corridor=True), PARAMS)
    seed = np.array([0.12, 0.04, math.radians(1.5)])
    found = register(source, target, seed, PARAMS)
    assert found is not None
    assert found.converged
    assert found.creeping
    assert found.accepted(PARAMS)
    assert found.iterations < PARAMS.iterations
    assert abs(found.pose[1]) < 0.005
    assert abs(found.pose[2]) < math.radians(0.05)
    sx, sy, syaw = np.sqrt(np.diag(found.covariance))
    assert sx >= PARAMS.max_distance_m * 0.999  # nothing measured along the axis
    assert sy < 0.02
    assert syaw < math.radians(0.5)
    checked_covariance(found.covariance, "registration")
    # A room holds the pose in every direction: converged without creeping.
    a, b = np.array([0.3, -0.2, 0.1]), np.array([-0.8, 0.6, 0.9])
    room = register(Cloud.of(_seen_from(_room(rng), b), PARAMS),
                    Cloud.of(_seen_from(_room(rng), a), PARAMS),
                    se2.between(a, b) + np.array([0.1, 0.1, 0.02]), PARAMS)  # fmt: skip
    assert room is not None
    assert room.converged
    assert not room.creeping


def test_creeping_needs_a_weak_direction_and_a_settled_rest() -> None:
    corridor = np.diag([1e-4, 1.0, 1.0])
    assert registration._creeping(corridor, np.array([0.01, 1e-5, 1e-5]))
    assert not registration._creeping(corridor, np.array([0.01, 1e-3, 1e-5]))
    assert not registration._creeping(np.eye(3), np.array([0.01, 1e-5, 1e-5]))
    turning = np.diag([1.0, 1.0, 1e-4])  # the weak direction is a turn: never converged so
    assert not registration._creeping(turning, np.array([1e-5, 1e-5, 0.01]))
    covariance = np.diag([0.01, 0.0001, 1e-6])
    wider = registration._unmeasured(covariance, np.diag([1e-3, 1.0, 1.0]), 0.3)
    assert wider[0, 0] == pytest.approx(0.09)
    assert wider[1, 1] == covariance[1, 1]
    assert registration._unmeasured(wider, np.diag([1e-3, 1.0, 1.0]), 0.2) is wider


def _slab_face(rng: np.random.Generator, x: float, n: int = 3000) -> np.ndarray:
    """Points on one face (at ``x``) of a 2 m wide slab in the room's middle, 0.2–2.5 m high."""
    face = np.c_[np.full(n, x), rng.uniform(-1.0, 1.0, n), rng.uniform(0.2, 2.5, n)]
    return face + rng.normal(0, 0.003, (n, 3))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_two_faces_of_a_thin_wall_do_not_pair_once_normals_face_their_scanner(
    seed: int,
) -> None:
    # Each robot sees the room and the face of an 8 cm slab on its side. Unoriented normals pair
    # the two faces and pull the answer towards each other by ~4 cm (measured 4.1-4.2); normals
    # turned towards the scanner keep the faces apart.
    rng = np.random.default_rng(seed)
    a, b = np.array([-1.5, 0.3, 0.2]), np.array([1.6, -0.4, math.pi - 0.3])
    seen_a = _seen_from(np.vstack([_room(rng), _slab_face(rng, -0.04)]), a)
    seen_b = _seen_from(np.vstack([_room(rng), _slab_face(rng, 0.04)]), b)
    truth = se2.between(a, b)
    start = truth + np.array([0.06, -0.04, math.radians(1.0)])

    def scanner(points: np.ndarray) -> np.ndarray:
        return np.broadcast_to(np.array([0.0, 0.0, 0.5]), points.shape)

    target = Cloud.of(seen_a, PARAMS, viewpoints=scanner(seen_a))
    source = Cloud.of(seen_b, PARAMS, viewpoints=scanner(seen_b))
    assert target.oriented
    assert source.oriented
    towards = (scanner(target.points) - target.points) * target.normals
    assert (towards.sum(axis=1) >= 0).all()
    found = register(source, target, start, PARAMS)
    assert found is not None
    assert found.accepted(PARAMS)
    assert math.dist(found.pose[:2], truth[:2]) < 0.005
    blind = register(Cloud.of(seen_b, PARAMS), Cloud.of(seen_a, PARAMS), start, PARAMS)
    assert blind is not None
    assert math.dist(blind.pose[:2], truth[:2]) > 0.03
    joined = Cloud.joined([target, source.moved(truth)])
    assert joined.oriented
    assert not Cloud.joined([target, Cloud.of(seen_b, PARAMS)]).oriented


def test_registration_of_clouds_that_do_not_overlap_is_none_or_refused() -> None:
    rng = np.random.default_rng(3)
    room = Cloud.of(_room(rng), PARAMS)
    far = room.moved(np.array([50.0, 0.0, 0.0]))
    assert register(far, room, np.zeros(3), PARAMS) is None
    assert register(Cloud.of(np.zeros((3, 3)), PARAMS), room, np.zeros(3), PARAMS) is None


def test_bad_seeds_priors_and_points_are_refused_in_one_line() -> None:
    rng = np.random.default_rng(4)
    room = Cloud.of(_room(rng), PARAMS)
    with pytest.raises(EstimationError, match="seed must be 3 finite numbers"):
        register(room, room, np.array([0.0, math.nan, 0.0]), PARAMS)
    with pytest.raises(EstimationError, match="positive definite"):
        register(room, room, np.zeros(3), PARAMS, prior=np.diag([1.0, 0.0, -1.0]))
    with pytest.raises(EstimationError, match="finite 3x3"):
        register(room, room, np.zeros(3), PARAMS, prior=np.eye(2))
    with_nan = np.vstack([_room(rng), [[math.nan, 0.0, 1.0], [math.inf, 1.0, 1.0]]])
    cloud = Cloud.of(with_nan, PARAMS)
    assert np.isfinite(cloud.points).all()
    assert np.isfinite(cloud.normals).all()
    views = np.zeros_like(with_nan)
    views[5] = math.nan  # a point whose viewpoint is unknown is dropped like a non-finite one
    assert len(Cloud.of(with_nan, PARAMS, viewpoints=views)) <= len(cloud)
    with pytest.raises(EstimationError, match="3 viewpoints for 4002 points"):
        Cloud.of(with_nan, PARAMS, viewpoints=np.zeros((3, 3)))
    with pytest.raises(EstimationError, match="cloud spans over"):
        Cloud.of(np.vstack([_room(rng), [[1e9, 0.0, 0.0]]]), PARAMS)


def test_clouds_move_join_and_crop_consistently() -> None:
    rng = np.random.default_rng(5)
    room = Cloud.of(_room(rng), PARAMS)
    pose = np.array([2.0, -1.0, 0.7])
    moved = room.moved(pose)
    assert np.allclose(np.linalg.norm(moved.normals, axis=1), np.linalg.norm(room.normals, axis=1))
    back = _seen_from(moved.points, pose)
    assert np.allclose(back, room.points, atol=1e-9)
    joined = Cloud.joined([room, moved])
    assert len(joined) == 2 * len(room)
    assert len(Cloud.joined([])) == 0
    near = room.within(np.zeros(2), 1.0)
    assert len(near) < len(room)
    assert (np.hypot(near.points[:, 0], near.points[:, 1]) <= 1.0).all()
    assert room.reach_m() == pytest.approx(np.hypot(3.0, 2.0), abs=0.1)


@pytest.mark.parametrize(
    "bad",
    [
        np.eye(2),
        np.diag([1.0, 1.0, -1.0]),
        [[1, 2, 3], [0, 1, 0], [0, 0, 1]],
        "x",
        np.full((3, 3), math.nan),
    ],
)
def test_a_localize_covariance_must_be_a_covariance(bad: object) -> None:
    with pytest.raises(EstimationError, match=r"Localize\.covariance"):
        checked_covariance(bad, "event 3: Localize.covariance")


def test_jacobi_eigenvectors_agree_with_lapack_including_degenerate_spectra() -> None:
    rng = np.random.default_rng(7)
    matrices = [m @ m.T for m in rng.normal(size=(200, 3, 3))]
    matrices += [np.diag([1.0, 1.0, 1e-9]), np.diag([2.0, 2.0, 2.0]), np.zeros((3, 3)),
                 np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])]  # fmt: skip
    for m in matrices:
        a, v = m.copy(), np.empty((3, 3))
        smallest = _jacobi3(a, v)
        values, vectors = np.linalg.eigh(m)
        np.testing.assert_allclose(v.T @ v, np.eye(3), atol=1e-12)  # orthonormal
        np.testing.assert_allclose(m @ v, v * np.diag(a), atol=1e-9 * max(1.0, values[-1]))
        assert a[smallest, smallest] == pytest.approx(values[0], abs=1e-9 * max(1.0, values[-1]))
        if values[1] - values[0] > 1e-6 * max(1.0, values[-1]):  # a unique smallest axis
            assert abs(v[:, smallest] @ vectors[:, 0]) == pytest.approx(1.0, abs=1e-9)


def test_normals_are_the_smallest_principal_axes_and_zero_without_neighbours() -> None:
    rng = np.random.default_rng(3)
    points = Cloud.of(_room(rng), PARAMS).points
    far = np.array([[50.0, 50.0, 1.0]])  # no neighbour within reach: no normal
    normals = _normals(np.vstack([points, far]), PARAMS)
    assert np.all(normals[-1] == 0.0)
    from scipy.spatial import cKDTree

    reach = 6.0 * PARAMS.voxel_m
    distance, index = cKDTree(points).query(points, k=PARAMS.neighbours, distance_upper_bound=reach)
    for i in rng.choice(len(points), 50, replace=False):
        near = points[index[i][np.isfinite(distance[i])]]
        _, vectors = np.linalg.eigh(np.cov(near.T))
        assert abs(normals[i] @ vectors[:, 0]) == pytest.approx(1.0, abs=1e-9)
    walls = np.abs(normals[:-1, 2]) < 0.5  # walls and pillar: horizontal normals
    assert walls.mean() > 0.95


def test_gauss_newton_kernel_matches_the_formula() -> None:
    rng = np.random.default_rng(5)
    points, targets = rng.normal(size=(40, 3)), rng.normal(size=(30, 3))
    normals = rng.normal(size=(30, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    index, ok = rng.integers(0, 30, 40), rng.random(40) < 0.7
    x, y, yaw, huber = 0.3, -0.2, 0.4, 0.5
    H, g = np.zeros((3, 3)), np.zeros(3)
    residual, weight = np.empty(ok.sum()), np.empty(ok.sum())
    _gauss_newton(points, targets, normals, index, ok, x, y, yaw, huber, H, g, residual, weight)
    c, s = math.cos(yaw), math.sin(yaw)
    p, n, t = points[ok], normals[index[ok]], targets[index[ok]]
    moved = np.c_[c * p[:, 0] - s * p[:, 1] + x, s * p[:, 0] + c * p[:, 1] + y, p[:, 2]]
    r = ((moved - t) * n).sum(axis=1)
    J = np.c_[n[:, 0], n[:, 1], n[:, 0] * (-s * p[:, 0] - c * p[:, 1])
              + n[:, 1] * (c * p[:, 0] - s * p[:, 1])]  # fmt: skip
    w = np.where(np.abs(r) <= huber, 1.0, huber / np.abs(r))
    np.testing.assert_allclose(residual, r, atol=1e-12)
    np.testing.assert_allclose(weight, w, atol=1e-12)
    np.testing.assert_allclose(H, J.T @ (J * w[:, None]), atol=1e-10)
    np.testing.assert_allclose(g, J.T @ (w * r), atol=1e-10)


@pytest.mark.parametrize(("apart", "settles"), [(3e-4, True), (5e-3, False)])
def test_a_registration_traded_between_two_matchings_settles_midway_only_when_they_are_close(
    monkeypatch: pytest.MonkeyPatch, apart: float, settles: bool
) -> None:
    """Two sets of nearest neighbours can hand the pose back and forth for every iteration
    there is (a generated building's scan link: 0.3 mm apart, 0.0 cm from the truth, refused as
    unconverged). Such a limit cycle has settled midway; one whose steps are millimetres has
    not."""
    rng = np.random.default_rng(1)
    a, b = np.array([0.3, -0.2, 0.1]), np.array([-0.8, 0.6, 0.9])
    target = Cloud.of(_seen_from(_room(rng), a), PARAMS)
    source = Cloud.of(_seen_from(_room(rng), b), PARAMS)
    truth = se2.between(a, b)
    ends = [truth + np.array([apart / 2, 0.0, -apart / 2]),
            truth - np.array([apart / 2, 0.0, -apart / 2])]  # fmt: skip
    real = registration._linearised
    calls = []

    def trading(*args: object) -> object:
        # The real system with its gradient replaced: each step lands on the other end.
        found = real(*args)
        if found is None:
            return None
        H, _, residuals, weights = found
        pose = args[3]
        calls.append(pose.copy())
        goal = ends[len(calls) % 2]
        return H, H @ registration._offset(pose, goal), residuals, weights

    monkeypatch.setattr(registration, "_linearised", trading)
    found = register(source, target, truth + np.array([0.02, -0.01, 0.01]), PARAMS)
    assert found is not None
    assert found.converged is settles
    if settles:
        assert found.accepted(PARAMS)
        np.testing.assert_allclose(found.pose, truth, atol=1e-6)
        assert found.iterations < 20
    else:
        assert found.iterations == PARAMS.iterations
        assert not found.accepted(PARAMS)


def test_a_limit_cycle_is_a_return_across_a_small_step() -> None:
    before = np.array([1.0, 2.0, math.pi - 1e-5])
    back = np.array([1.0 + 5e-5, 2.0, -math.pi + 1e-5])  # across the ±π seam
    assert registration._cycled(back, before, np.array([4e-4, 0.0, 4e-4]))
    assert not registration._cycled(back, before, np.array([2e-3, 0.0, 0.0]))  # steps too long
    assert not registration._cycled(back + np.array([0.0, 2e-4, 0.0]), before,
                                    np.array([4e-4, 0.0, 0.0]))  # fmt: skip


def test_a_registration_that_slid_far_from_its_seed_is_not_accepted() -> None:
    """Past twice the reach its seed is good to, a converged registration with every point an
    inlier is still refused: it slid along what the points do not constrain."""
    from estimation.search.registration import Registration

    def ended(moved_m: float) -> Registration:
        return Registration(np.zeros(3), np.eye(3), 1.0, 0.001, 5, True, 1000, moved_m)

    assert ended(0.0).accepted(PARAMS)
    assert ended(2 * PARAMS.max_distance_m).accepted(PARAMS)
    assert not ended(2 * PARAMS.max_distance_m + 0.01).accepted(PARAMS)
    assert not Registration(np.zeros(3), np.eye(3), 1.0, 0.001, 40, False, 1000).accepted(PARAMS)


def test_the_points_left_out_of_lookups_have_no_target_within_reach_at_any_later_pose() -> None:
    """``_Near`` looks up only the source points that had a target within reach plus a margin
    where they were last checked; at every pose the registration visits after, each point with
    a target within reach is among them (the pruning changes nothing), and it checks again once
    the pose has moved a point beyond the margin."""
    rng = np.random.default_rng(7)
    target = Cloud.of(_room(rng), PARAMS)
    source = Cloud.of(_seen_from(_room(rng), np.array([1.5, 0.5, 0.3])), PARAMS)
    lookup = _Near(target, PARAMS.max_distance_m)
    seed = np.array([1.0, 0.0, 0.2])
    first = lookup.rows(source, seed)
    assert 0 < len(first) < len(source)
    for step in rng.uniform(-1.0, 1.0, (60, 3)) * np.array([0.12, 0.12, 0.02]):
        pose = seed + step
        rows = lookup.rows(source, pose)
        nearest = target.grid.query(_moved(source.points, pose), 1, PARAMS.max_distance_m)
        within = np.flatnonzero(nearest[:, 0] < len(target))
        assert np.isin(within, rows).all()
    far = seed + np.array([0.0, 0.0, 0.1])  # 0.1 rad turns the outer points by decimetres
    assert not np.array_equal(lookup.rows(source, far), first)


def test_a_registration_stops_once_it_has_slid_past_the_limit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Refused however it would end, a registration that has slid past the limit stops there
    instead of spending its iterations (office_loop: 6 of 45 ran all 40)."""
    from estimation.search import registration

    rng = np.random.default_rng(1)
    a, b = np.array([0.3, -0.2, 0.1]), np.array([-0.8, 0.6, 0.9])
    target = Cloud.of(_seen_from(_room(rng), a), PARAMS)
    source = Cloud.of(_seen_from(_room(rng), b), PARAMS)
    seed = se2.between(a, b) + np.array([0.25, -0.2, math.radians(4.0)])
    free = register(source, target, seed, PARAMS)
    assert free is not None
    assert free.accepted(PARAMS)
    assert free.moved_m > 0.3
    monkeypatch.setattr(registration, "_MAX_SLIDE", 0.5)  # 15 cm
    stopped = register(source, target, seed, PARAMS)
    assert stopped is not None
    assert not stopped.converged
    assert not stopped.accepted(PARAMS)
    assert 0.15 < stopped.moved_m < free.moved_m
    assert stopped.iterations < free.iterations
