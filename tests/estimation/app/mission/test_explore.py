"""The explorer's choices on the estimated map: poses taken, frontiers tracked and given up,
rooms nobody stood in, turns tied through pivots, robots in the way."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimation.app.mission import explore
from estimation.app.mission.explore import Explorer, StallWatch, Target
from estimation.app.mission.view import MapView
from mapping.grid import OccupancyGrid
from mapping.traversability import Frontier
from tests.estimation.app.mission.conftest import (
    CONFIG,
    RES,
    glimpsed,
    seen_whole,
)


def test_poses_already_taken_are_the_same_within_30_cm_and_30_degrees() -> None:
    explorer = Explorer(CONFIG, (1.5, 4.5))
    explorer.taken.append(np.array([2.0, 2.0, math.radians(178.0)]))
    assert explorer._taken(np.array([2.0, 2.0, math.radians(178.0)]))
    assert explorer._taken(np.array([2.2, 1.8, math.radians(-160.0)]))  # 22° across ±180°
    assert explorer._taken(np.array([2.0, 2.0, math.radians(178.0 + 360.0)]))
    assert not explorer._taken(np.array([2.25, 2.25, math.radians(178.0)]))  # 35 cm away
    assert not explorer._taken(np.array([2.0, 2.0, math.radians(140.0)]))  # 38° off
    assert not Explorer(CONFIG, (1.5, 4.5))._taken(np.zeros(3))


def test_a_scan_pose_taken_is_not_offered_again(view: MapView) -> None:
    explorer = Explorer(CONFIG, (1.5, 3.5))
    reference = np.array([2.5, 2.0, 0.0])
    mapper = np.array([1.0, 1.0, 0.0])
    first = explorer.scan_pose(view, reference, mapper, [reference], None, [])
    assert first is not None
    assert view.space.is_free(first.pose[:2])
    assert view.geometry.mutual(reference, first.pose, (1.5, 3.5))
    np.testing.assert_allclose(first.path[0], mapper[:2])
    np.testing.assert_allclose(first.path[-1], first.pose[:2])
    explorer.taken.append(first.pose)
    second = explorer.scan_pose(view, reference, mapper, [reference], None, [])
    assert second is not None
    assert not explorer._taken(second.pose)  # another place, or the same facing elsewhere
    assert second.score <= first.score  # the best was the first
    # ``exclude`` (a pose that failed) keeps the mapper 30 cm away from it, whatever the yaw.
    third = Explorer(CONFIG, (1.5, 3.5)).scan_pose(view, reference, mapper, [reference], None,
                                                   [first.pose])  # fmt: skip
    assert third is not None
    assert math.dist(third.pose[:2], first.pose[:2]) >= 0.3


def frontier_at(x: float, y: float) -> Frontier:
    return Frontier(np.zeros((5, 2), dtype=np.int64), np.array([x, y]), 5)


def cells_at(view: MapView, x: float, y: float) -> Frontier:
    """A frontier of five cells in a row from the cell at (x, y)."""
    row, col = view.space.cell(np.array([x, y]))
    cells = np.array([[row, col + k] for k in range(5)], dtype=np.int64)
    return Frontier(cells, np.array([x, y]), 5)


def two_frontiers(
    view: MapView, monkeypatch: pytest.MonkeyPatch, far_first: bool = False
) -> tuple[Frontier, Frontier, Explorer, list[np.ndarray]]:
    """A frontier near the robot at (1, 1) and one far from it (the only ones the view shows),
    a new explorer and the robot's place."""
    near, far = cells_at(view, 1.5, 1.0), cells_at(view, 5.0, 3.0)
    shown = [far, near] if far_first else [near, far]
    monkeypatch.setattr(explore, "frontiers", lambda *args, **kwargs: shown)
    return near, far, Explorer(CONFIG, (1.5, 4.5)), [np.array([1.0, 1.0])]


def test_a_frontier_that_does_not_come_closer_is_given_up_and_offered_when_it_is_all_left(
    view: MapView,
) -> None:
    explorer = Explorer(CONFIG, (1.5, 4.5))
    robots = [np.array([1.0, 1.0])]
    found = explorer.frontier(view, robots)
    assert found is not None
    assert 6.1 < found.centroid_xy[0] < 6.9  # before the unseen back of room B
    assert found.size >= 5
    distance = float(np.min(view.distances_from(robots)[found.cells[:, 0], found.cells[:, 1]]))
    assert distance == pytest.approx(math.dist(robots[0], found.centroid_xy), rel=0.2)

    def give_up() -> None:
        assert not explorer.progress(found, distance, view)  # a new target
        assert explorer.target is not None
        for station in range(explore._PATIENCE):
            assert explorer.target is not None
            # Closer, but by less than 30 cm, and the map around it the same: not nearer.
            assert not explorer.progress(found, distance - 0.05 * station, view)
        assert explorer.target is None

    give_up()
    assert len(explorer.given_up) == 1
    np.testing.assert_allclose(explorer.given_up[0], found.centroid_xy)
    # The only frontier left was given up: it is tried once more, then no more.
    again = explorer.frontier(view, robots)
    assert again is not None
    np.testing.assert_allclose(again.centroid_xy, found.centroid_xy)
    assert explorer.given_up == []
    assert len(explorer.retried) == 1
    give_up()
    assert len(explorer.given_up) == 1
    # Given up twice it is still offered (the loop's stall rule ends the exploring), and it
    # stays given up
    third = explorer.frontier(view, robots)
    assert third is not None
    np.testing.assert_allclose(third.centroid_xy, found.centroid_xy)
    assert len(explorer.given_up) == 1
    assert len(explorer.retried) == 1
    assert explorer.frontier(view, [np.array([-50.0, -50.0])]) is None  # from nowhere


def test_a_frontier_that_comes_closer_or_recedes_as_the_map_grows_is_kept(
    view: MapView, monkeypatch: pytest.MonkeyPatch
) -> None:
    explorer = Explorer(CONFIG, (1.5, 4.5))
    assert not explorer.progress(frontier_at(6.5, 2.0), 6.0, view)
    for station in range(4 * explore._PATIENCE):  # 0.5 m nearer at each station
        assert explorer.progress(frontier_at(6.5, 2.0 + 0.1 * station), 5.5 - 0.5 * station,
                                 view)  # fmt: skip
    assert explorer.given_up == []
    assert explorer.target is not None
    assert explorer.target.best_m == pytest.approx(5.5 - 0.5 * (4 * explore._PATIENCE - 1))
    # Stalling counts from the last gain; a frontier that jumped (> 1.5 m) is a new target.
    assert not explorer.progress(frontier_at(6.5, 2.8), 10.0, view)
    assert explorer.target.stale == 1
    assert not explorer.progress(frontier_at(3.0, 2.8), 10.0, view)
    assert explorer.target.stale == 0
    assert explorer.target.best_m == 10.0
    # No nearer, but the known floor around it grows by 0.5 m² or more per station: kept;
    # by less: given up.
    known = iter([20.0, 20.6, 21.2, 21.8, 22.4, 22.6, 22.8, 23.0])
    monkeypatch.setattr(explore, "_known_near", lambda view, xy: next(known))
    explorer.progress(frontier_at(1.0, 1.0), 4.0, view)
    for _ in range(4):
        explorer.progress(frontier_at(1.0, 1.0), 4.0, view)
        assert explorer.target is not None
        assert explorer.target.stale == 0
    for stale in range(1, explore._PATIENCE):
        explorer.progress(frontier_at(1.0, 1.0), 4.0, view)
        assert explorer.target is not None
        assert explorer.target.stale == stale
    explorer.progress(frontier_at(1.0, 1.0), 4.0, view)
    assert explorer.target is None
    assert len(explorer.given_up) == 1
    explorer.progress(None, 0.0, view)
    assert explorer.target is None


def test_a_stalled_exploration_goes_on_only_at_a_frontier_never_tried(
    view: MapView, monkeypatch: pytest.MonkeyPatch
) -> None:
    near, far = cells_at(view, 1.5, 1.0), cells_at(view, 5.0, 3.0)
    blocked = Frontier(np.array([[0, 0]] * 5, dtype=np.int64), np.array([5.5, 3.0]), 5)
    monkeypatch.setattr(explore, "frontiers", lambda *args, **kwargs: [near, far, blocked])
    explorer = Explorer(CONFIG, (1.5, 4.5))
    robots = [np.array([1.0, 1.0])]
    explorer.progress(near, 0.5, view)
    assert explorer.abandon(view, robots)  # the target is given up; far was never tried
    assert explorer.target is None
    np.testing.assert_allclose(explorer.given_up, [near.centroid_xy])
    assert explorer.frontier(view, robots) is far
    explorer.retried.append(far.centroid_xy.copy())  # tried once more already
    assert not explorer.abandon(view, robots)  # only the unreachable one is left untried
    assert not explorer.abandon(view, [np.array([-50.0, -50.0])])  # nowhere to start from


def test_the_pair_keeps_its_target_frontier_while_it_is_reachable_and_not_given_up(
    view: MapView, monkeypatch: pytest.MonkeyPatch
) -> None:
    near, far, explorer, robots = two_frontiers(view, monkeypatch, far_first=True)
    assert explorer.frontier(view, robots) is near  # no target yet: the nearest
    explorer.progress(far, 4.5, view)  # the pair works on the far one
    assert explorer.frontier(view, robots) is far
    moved = cells_at(view, 4.4, 3.3)  # the target receded as the map grew: still the target
    monkeypatch.setattr(explore, "frontiers", lambda *args, **kwargs: [near, moved])
    assert explorer.frontier(view, robots) is moved
    explorer.given_up.append(moved.centroid_xy.copy())  # given up: the nearest again
    assert explorer.frontier(view, robots) is near
    explorer.given_up.clear()
    blocked = Frontier(np.array([[0, 0]] * 5, dtype=np.int64), np.array([5.5, 3.0]), 5)
    monkeypatch.setattr(explore, "frontiers", lambda *args, **kwargs: [near, blocked])
    assert explorer.frontier(view, robots) is near  # the target unreachable: the nearest


def test_a_turn_is_tied_at_once_or_through_pivots_seen_before_and_after_each_part(
    view: MapView,
) -> None:
    explorer = Explorer(CONFIG, (1.5, 3.5))
    reference = np.array([2.5, 2.0, math.radians(30.0)])
    found = explorer.scan_pose(view, reference, np.array([1.0, 1.0, 0.0]), [reference], None, [])
    assert found is not None
    mapper = found.pose  # where the reference sees its beacon, facing it
    wide = (0.5, CONFIG.beacon.max_range_m)
    assert view.geometry.mutual(reference, mapper, wide)
    pivots: dict[int, int] = {}
    for degrees in range(0, 360, 15):
        heading = math.radians(degrees)
        chain = explorer.tie(view, reference, heading, mapper, [reference])
        turn = abs(math.remainder(heading - reference[2], 2 * math.pi))
        if chain is None:
            continue
        assert len(chain) == max(1, math.ceil(turn / explore._PART_RAD - 1e-9))
        assert chain[-1][0] == heading
        before, at = reference, mapper
        for after_yaw, pivot in chain:
            after = np.array([2.5, 2.0, after_yaw])
            assert abs(math.remainder(after_yaw - before[2], 2 * math.pi)) <= (
                explore._PART_RAD + 1e-9
            )
            if pivot is None:
                assert view.geometry.mutual(after, at, wide)  # the mapper sees it already
            else:
                # Seen from the reference before the part and after it, on drivable floor,
                # reached along a path from where the mapper stood.
                assert view.geometry.mutual(before, pivot.pose, explorer.band)
                assert view.geometry.mutual(after, pivot.pose, explorer.band)
                assert view.space.is_free(pivot.pose[:2])
                np.testing.assert_allclose(pivot.path[0], at[:2], atol=0.15)
                np.testing.assert_allclose(pivot.path[-1], pivot.pose[:2])
                at = pivot.pose
            before = after
        pivots[degrees] = sum(1 for _, p in chain if p is not None)
    assert pivots[30] == 0  # no turn at all
    assert {0, 1, 2} <= set(pivots.values())
    # Facing the room's back wall (x = 0), 2.5 m behind: no pose 1.5 m off in front.
    assert not {165, 180, 195} & set(pivots)


def test_a_turn_no_pivot_can_tie_is_taken_untied(view: MapView) -> None:
    explorer = Explorer(CONFIG, (1.5, 3.5))
    # The mapper in the closet behind a wall without a door: it reaches no pivot.
    reference = np.array([3.0, 2.0, 0.0])
    closet = np.array([9.0, 2.0, math.pi])
    assert explorer.tie(view, reference, math.radians(90.0), closet, [reference]) is None
    plan = explorer.heading(view, reference, closet, [reference], None)
    assert plan is None  # nor any mapper pose around the reference it could reach
    explorer_b = Explorer(CONFIG, (1.5, 3.5))
    mapper = np.array([1.0, 1.0, 0.0])
    plan = explorer_b.heading(view, reference, mapper, [reference], None)
    assert plan is not None
    assert plan.tied
    assert plan.parts[-1][0] == plan.heading
    assert plan.pivots == sum(1 for _, p in plan.parts if p is not None)
    # When no heading's turn can be tied: the best heading with a mapper pose, untied, and
    # no untied turn only to look.
    untieable = Explorer(CONFIG, (1.5, 3.5))
    untieable.tie = lambda *args, **kwargs: None  # type: ignore[method-assign]
    untied = untieable.heading(view, reference, mapper, [reference], None)
    assert untied is not None
    assert not untied.tied
    assert untied.parts == ((untied.heading, None),)
    assert untied.pivots == 0
    # Looking first changes nothing here: the untied heading has a mapper pose
    looked = untieable.heading(view, reference, mapper, [reference], None, look_first=True)
    assert looked is not None
    assert (looked.heading, looked.tied) == (untied.heading, False)


def test_an_untied_turn_wins_only_by_more_than_its_cost(
    view: MapView, monkeypatch: pytest.MonkeyPatch
) -> None:
    from estimation.app.mission import explore

    reference, mapper = np.array([3.0, 2.0, 0.0]), np.array([1.0, 1.0, 0.0])
    tied = Explorer(CONFIG, (1.5, 3.5)).heading(view, reference, mapper, [reference], None)
    assert tied is not None
    assert tied.tied
    monkeypatch.setattr(explore, "_UNTIED_COST", 1e9)
    again = Explorer(CONFIG, (1.5, 3.5)).heading(view, reference, mapper, [reference], None)
    assert again is not None
    assert (again.heading, again.tied, again.pivots) == (tied.heading, True, tied.pivots)
    # Free to take: the best-scored heading with a mapper pose, untied
    monkeypatch.setattr(explore, "_UNTIED_COST", -1.0)
    free = Explorer(CONFIG, (1.5, 3.5)).heading(view, reference, mapper, [reference], None)
    assert free is not None
    assert not free.tied
    assert free.parts == ((free.heading, None),)
    if tied.pivots == 0:
        assert free.heading == tied.heading  # the tied plan was the best heading already


def test_a_turn_only_to_look_may_be_taken_untied(
    view: MapView, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The reference in room A faces its mapper, away from the door to room B, whose back
    nobody has seen. No mapper pose is known beyond the door, so facing it is a turn only to
    look; no chain of pivots ties a half turn there. It is taken untied when it beats every
    tied heading by more than the untied cost: otherwise the robot at the front of a pair keeps
    facing back (generated building 0: 20 stations to cross a 3.3 m × 4.8 m office, 5 with
    this)."""
    from estimation.app.mission.explore import _reachable_targets

    reference, mapper = np.array([5.0, 2.0, math.pi]), np.array([2.5, 2.0, 0.0])
    found = _reachable_targets(view, [reference[:2], mapper[:2]], [])
    frontier = min(found, key=lambda item: item[1])[0]
    assert frontier.centroid_xy[0] > 6.0  # the door to room B
    plain = Explorer(CONFIG, (1.5, 3.5)).heading(view, reference, mapper, [reference], frontier)
    assert plain is not None
    assert abs(math.remainder(plain.heading - math.pi, 2 * math.pi)) < math.radians(90.0)
    looked = Explorer(CONFIG, (1.5, 3.5)).heading(
        view, reference, mapper, [reference], frontier, look_first=True
    )
    assert looked is not None
    assert not looked.tied
    assert looked.parts == ((looked.heading, None),)
    assert abs(math.remainder(looked.heading, 2 * math.pi)) <= math.radians(30.0)  # the door
    monkeypatch.setattr(explore, "_UNTIED_COST", 1e9)
    costly = Explorer(CONFIG, (1.5, 3.5)).heading(
        view, reference, mapper, [reference], frontier, look_first=True
    )
    assert costly is not None
    assert costly.tied


def test_no_scan_pose_is_planned_with_a_third_robot_between_the_beacons(view: MapView) -> None:
    """A third robot on the line from the reference to the best scan pose hides the beacon (or
    shows its own in its place): the next best pose clear of it is planned instead."""
    reference = np.array([2.5, 2.0, 0.0])
    mapper = np.array([1.0, 1.0, 0.0])
    first = Explorer(CONFIG, (1.5, 3.5)).scan_pose(view, reference, mapper, [reference], None, [])
    assert first is not None
    between = reference[:2] + 0.5 * (first.pose[:2] - reference[:2])
    third = np.array([between[0], between[1], 0.0])
    clear = Explorer(CONFIG, (1.5, 3.5)).scan_pose(view, reference, mapper, [reference, third],
                                                   None, [])  # fmt: skip
    assert clear is not None
    assert math.dist(clear.pose[:2], first.pose[:2]) > 0.1
    radius = CONFIG.robot.footprint_radius_m
    assert not explore._in_the_way(reference[:2], clear.pose[:2], [reference, third], radius)


def test_a_robot_is_in_the_way_only_beside_the_segment_between_the_beacons() -> None:
    a, b, radius = np.array([0.0, 0.0]), np.array([4.0, 0.0]), 0.3
    assert explore._in_the_way(a, b, [np.array([2.0, 0.5])], radius)  # 0.5 < 0.3 + 0.3
    assert not explore._in_the_way(a, b, [np.array([2.0, 0.7])], radius)
    assert not explore._in_the_way(a, b, [np.array([5.0, 0.0])], radius)  # 1 m behind b
    assert explore._in_the_way(a, b, [np.array([4.5, 0.0])], radius)  # behind b, in reach
    assert not explore._in_the_way(a, b, [a.copy()], radius)  # the robot at a itself
    assert not explore._in_the_way(a, a, [np.array([1.0, 0.0])], radius)  # 1 m from a point


def room_b() -> tuple[OccupancyGrid, list[np.ndarray], MapView, Explorer, Target]:
    """Rooms A and B seen whole, the robots in room A, and the target the explorer picks."""
    grid = seen_whole()
    robots = [np.array([2.5, 2.0]), np.array([1.0, 1.0])]
    view = MapView(grid, CONFIG, np.array(robots))
    explorer = Explorer(CONFIG, (1.5, 4.5))
    room = explorer.frontier(view, robots)
    assert room is not None
    return grid, robots, view, explorer, room


def test_once_no_frontier_is_left_the_pair_goes_into_the_rooms_nobody_stood_in() -> None:
    grid, robots, view, explorer, room = room_b()
    assert 5.6 < room.centroid_xy[0] < 6.5  # room B, seen whole through its door
    distance = float(np.min(view.distances_from(robots)[room.cells[:, 0], room.cells[:, 1]]))
    assert 1.5 < distance < 4.5
    # The pair heads there as to a frontier; a robot standing in room B has entered it.
    reference, mapper = np.array([2.5, 2.0, 0.0]), np.array([1.0, 1.0, 0.0])
    goal = explorer.scan_pose(view, reference, mapper, [reference], room, [])
    assert goal is not None
    assert goal.pose[0] > 4.5  # through the door
    inside = MapView(grid, CONFIG, np.array([*robots, [5.5, 2.0]]))
    assert explorer.frontier(inside, robots) is None
    # A frontier not given up comes first; given up, the room is offered again.
    door = Frontier(room.cells, room.centroid_xy + np.array([0.0, 5.0]), room.size)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(explore, "frontiers", lambda *args, **kwargs: [door])
        assert explorer.frontier(view, robots) is door
        explorer.given_up.append(door.centroid_xy.copy())
        offered = explorer.frontier(view, robots)
        assert offered is not None
        assert not isinstance(offered, Frontier)
        assert explorer.abandon(view, robots)  # the room was never tried


def test_a_frontier_seen_only_through_a_doorway_is_looked_at_from_the_drivable_floor() -> None:
    robots = [np.array([1.0, 0.5]), np.array([2.0, 3.0])]
    view = MapView(glimpsed(), CONFIG, np.array(robots))
    reach = view.distances_from(robots)
    res = view.floor.resolution_m
    found = explore.frontiers(view.floor, view.space, robot_radius_m=view.radius_m,
                              min_cells=5, min_unknown_m2=explore.MIN_UNKNOWN_M2)  # fmt: skip
    (far,) = [f for f in found if f.centroid_xy[0] > 5.0]  # at the far end of the sliver
    assert not np.isfinite(reach[far.cells[:, 0], far.cells[:, 1]]).any()  # no path there
    targets = {round(float(t.centroid_xy[0]), 2): (t, d)
               for t, d in explore._reachable_targets(view, robots, [])}  # fmt: skip
    looked, distance = targets[round(float(far.centroid_xy[0]), 2)]
    assert isinstance(looked, Frontier)
    np.testing.assert_allclose(looked.centroid_xy, far.centroid_xy)
    assert looked.size == far.size
    # From the drivable floor of room A and its doorway, within 2 m, over free floor.
    xy = view.floor.lower_xy + (looked.cells[:, ::-1] + 0.5) * res
    assert np.isfinite(reach[looked.cells[:, 0], looked.cells[:, 1]]).all()
    assert (xy[:, 0] < 4.5).all()
    assert (xy[:, 0] > 2.0).all()
    assert np.abs(xy[:, 1] - 2.0).max() < 1.0  # in front of the door
    far_xy = view.floor.lower_xy + (far.cells[:, ::-1] + 0.5) * res
    gap = np.hypot(*(xy[:, None, :] - far_xy[None, :, :]).transpose(2, 0, 1)).min(axis=1)
    assert gap.max() <= explore._LOOK_M + 1e-9
    assert distance == pytest.approx(float(reach[looked.cells[:, 0], looked.cells[:, 1]].min()))
    assert 1.0 < distance < 3.0
    # The pair heads for it once the doorway's own frontier is given up.
    explorer = Explorer(CONFIG, (1.5, 4.5))
    near = [t.centroid_xy for t, _ in targets.values() if t.centroid_xy[0] < 5.0]
    explorer.given_up.extend(np.array(c) for c in near)
    chosen = explorer.frontier(view, robots)
    assert chosen is not None
    np.testing.assert_allclose(chosen.centroid_xy, far.centroid_xy)
    assert len(chosen.cells) == len(looked.cells)


def test_a_frontier_seen_through_a_window_is_not_looked_at() -> None:
    robots = [np.array([1.0, 0.5]), np.array([2.0, 3.0])]
    view = MapView(glimpsed(door=False), CONFIG, np.array(robots))
    found = explore.frontiers(view.floor, view.space, robot_radius_m=view.radius_m,
                              min_cells=5, min_unknown_m2=explore.MIN_UNKNOWN_M2)  # fmt: skip
    assert any(f.centroid_xy[0] > 5.0 for f in found)  # the sliver's frontier is there
    assert explore._reachable_targets(view, robots, []) == []  # the wall hides it
    assert Explorer(CONFIG, (1.5, 4.5)).frontier(view, robots) is None


def test_a_frontier_beyond_the_look_distance_is_not_looked_at(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    robots = [np.array([1.0, 0.5]), np.array([2.0, 3.0])]
    view = MapView(glimpsed(), CONFIG, np.array(robots))
    monkeypatch.setattr(explore, "_LOOK_M", 0.5)  # the sliver's drivable end is farther
    targets = explore._reachable_targets(view, robots, [])
    assert targets  # the doorway's own frontier
    assert all(t.centroid_xy[0] < 5.0 for t, _ in targets)


def test_a_stalled_exploration_tries_each_given_up_frontier_once_more_but_not_the_last(
    view: MapView, monkeypatch: pytest.MonkeyPatch
) -> None:
    near, far, explorer, robots = two_frontiers(view, monkeypatch)
    explorer.given_up.append(far.centroid_xy.copy())  # given up early on
    explorer.progress(near, 0.5, view)  # the target when the loop stalls
    assert explorer.abandon(view, robots)  # far is tried once more
    np.testing.assert_allclose(explorer.retried, [far.centroid_xy])
    np.testing.assert_allclose(explorer.given_up, [near.centroid_xy])  # not the one just left
    chosen = explorer.frontier(view, robots)
    assert chosen is far
    explorer.progress(far, 4.0, view)
    assert not explorer.abandon(view, robots)  # every frontier tried twice: exploring ends
    # Nothing given up that is still there: nothing to try again.
    fresh = Explorer(CONFIG, (1.5, 4.5))
    fresh.given_up.append(np.array([30.0, 30.0]))
    fresh.progress(near, 0.5, view)
    fresh.progress(far, 4.0, view)  # a new target; near is not given up
    fresh.retried.append(near.centroid_xy.copy())
    assert not fresh.abandon(view, robots)  # far just left; near tried again already


def test_progress_is_the_floor_known_around_where_the_frontier_was(
    view: MapView, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A corridor mapped station by station: its frontier moves on by a metre each time, and
    # around each new place less is known than around the last; the robots come no nearer.
    known = {}

    def known_near(_view: MapView, xy: np.ndarray) -> float:
        return known[round(float(xy[0]), 1)]

    monkeypatch.setattr(explore, "_known_near", known_near)
    explorer = Explorer(CONFIG, (1.5, 4.5))
    for station in range(4 * explore._PATIENCE):
        x = 1.0 + station
        known[round(x - 1.0, 1)] = 12.0  # where it was: mapped since
        known[round(x, 1)] = 6.0  # where it is now: half unknown
        explorer.progress(frontier_at(x, 2.0), 3.0, view)
        assert explorer.target is not None
        assert explorer.target.stale == 0
    # The frontier stays where it is and nothing more is seen there: given up.
    for stale in range(1, explore._PATIENCE + 1):
        explorer.progress(frontier_at(x, 2.0), 3.0, view)
        assert (explorer.target is None) == (stale == explore._PATIENCE)
    assert len(explorer.given_up) == 1


def test_exploring_stalls_when_the_floor_stops_growing_but_not_on_the_way_to_a_target() -> None:
    n = explore._STALL_STATIONS
    watch = StallWatch()
    grown = [100.0 + 10.0 * k for k in range(5)]  # mapping
    assert not any(watch.add(m2, nearer=False) for m2 in grown)
    flat = [watch.add(grown[-1] + 0.1 * k, nearer=False) for k in range(1, n + 2)]
    assert flat == [False] * (n - 1) + [True, True]  # n stations that added less than 2 m²
    # Driving to a far frontier adds no floor but comes nearer at each station: no stall.
    watch = StallWatch()
    assert not any(watch.add(100.0, nearer=True) for _ in range(3 * n))
    assert len(watch.known) == 1
    # The window then counts from the last station that came nearer.
    assert not any(watch.add(100.0, nearer=False) for _ in range(n - 1))
    assert watch.add(100.0, nearer=False)
    watch.restart()  # the loop goes on at another frontier
    assert watch.known == [100.0]
    assert not watch.add(100.5, nearer=False)
    assert "2 m² over 10 stations" in StallWatch.why()


def test_a_targets_cells_count_from_the_map_it_was_found_on_as_the_map_grows() -> None:
    """Generated building 104, three robots: the map grew west during a station, the next
    view's floor map began 1.5 m further west, and the target's cells, indexed on the old one,
    pointed 15 cells east of the target (and past the map's edge: the mission crashed)."""
    grid, robots, view, explorer, room = room_b()
    assert explorer.frame_xy is not None
    where = view.floor.lower_xy + (room.cells[:, ::-1] + 0.5) * RES
    # The map grows: floor seen 1.5 m west of the rooms' wall.
    cells, values = grid.cells()
    extra = np.array([[i, j, k] for i in range(-16, -1) for j in range(0, 40) for k in range(3)])
    grown = MapView(
        OccupancyGrid.from_cells(grid.params, np.vstack([cells, extra]),
                                 np.concatenate([values, np.full(len(extra), -2.0)])),
        CONFIG, np.array(robots),
    )  # fmt: skip
    assert grown.floor.lower_xy[0] == pytest.approx(view.floor.lower_xy[0] - 1.5, abs=1e-9)
    np.testing.assert_allclose(explorer.centres(grown, room), where, atol=1e-9)
    expected = grown.distances_from(list(where))
    np.testing.assert_array_equal(explorer._goal_field(grown, room), expected)
    # Counted from the grown map's corner, the same cells lie 1.5 m west of the target.
    naive = grown.floor.lower_xy + (room.cells[:, ::-1] + 0.5) * RES
    np.testing.assert_allclose(naive - where, [[-1.5, 0.0]] * len(where), atol=1e-9)
