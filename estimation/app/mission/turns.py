"""The reference's turn at a station, tied by pivots (docs/mission-loop.md, "Every turn is
tied"): the mission loop flies a :class:`~estimation.app.mission.explore.TurnPlan` here."""

from __future__ import annotations

import math
from typing import Any, Protocol

import numpy as np

from estimation.app.mission.explore import Explorer, ScanGoal, TurnPlan
from estimation.app.mission.fleet import Fleet
from estimation.app.mission.view import MapView
from estimation.app.sim.planning import as_spec
from sensors.sim.mission import StepSpec

__all__ = ["RETRIES", "Spec", "fly_turn"]

#: A planned mutual observation (a scan pose, a pivot) that failed is retried from this many
#: other poses.
RETRIES = 2
#: A pose as the mission file writes it (x_m, y_m, yaw_deg), or None.
Spec = list[float] | None


class TurningLoop(Protocol):
    """What a turn needs of the mission loop (:class:`~estimation.app.mission.loop.MissionLoop`)."""

    fleet: Fleet
    robots: list[str]
    index: dict[str, int]
    steps: list[StepSpec]
    pivots: int
    retries: list[str]
    untied: dict[str, str]

    def pose(self, robot: str) -> np.ndarray: ...
    def go(self, robot: str, pose: np.ndarray, path: list[np.ndarray] | None) -> bool: ...
    def dwell(self, **fields: Any) -> bool: ...
    def view(self) -> MapView | None: ...


def fly_turn(loop: TurningLoop, explorer: Explorer, reference: str, mapper: str,
             plan: TurnPlan, at: Spec) -> Spec:  # fmt: skip
    """Fly a :class:`TurnPlan`. Before each part the mapper drives to its pivot and both
    robots dwell (the mutual observation ties the pivot to the reference before the part);
    the reference turns and both dwell (the observation ties the turned reference to the
    pivot). A pivot refused or not observed is replaced by another, up to ``RETRIES``
    times; after that the rest of the turn is untied: the reference turns to the final
    heading at once. Returns the last turn's pose (the station's ``at``), or ``at`` if the
    reference did not turn."""
    why = None if plan.tied else "no chain of pivots"
    turned = False
    for heading, planned in plan.parts:
        final = heading
        if planned is not None:
            seen, at = _fly_pivot(loop, explorer, reference, mapper, planned, heading, at)
            if not seen:
                why, final = why or "no pivot observed", plan.heading
        ref_pose = loop.pose(reference)
        target = np.array([ref_pose[0], ref_pose[1], final])
        if abs(math.remainder(final - ref_pose[2], 2 * math.pi)) > 1e-6 and loop.go(
            reference, target, [ref_pose[:2], ref_pose[:2]]
        ):
            at = as_spec(target)
            seen = loop.dwell(phase="station", reference=reference, mapper=mapper,
                              step=len(loop.steps))  # fmt: skip
            if not seen:
                why = why or "the turned reference did not see the pivot"
            turned = True
            explorer.taken.append(loop.pose(reference))
        if final == plan.heading:
            break
    if turned and why is not None:
        loop.untied[f"{reference}{loop.index[reference]}"] = why
    return at


def _fly_pivot(loop: TurningLoop, explorer: Explorer, reference: str, mapper: str,
               goal: ScanGoal | None, heading: float, at: Spec) -> tuple[bool, Spec]:  # fmt: skip
    """Drive the mapper to a pivot for the reference's turn to ``heading`` and dwell; on a
    refused goal or a missed observation, the next pivot. Each pivot taken closes a step of
    the mission as flown (``at``, the turn before it, and the pivot as its one scan).
    Returns whether a pivot was observed, and the ``at`` of the step now open."""
    failed: list[np.ndarray] = []
    for _ in range(RETRIES + 1):
        if goal is None:
            view = loop.view()
            if view is None:
                break
            before = loop.pose(reference)
            after = np.array([before[0], before[1], heading])
            others = [loop.pose(n) for n in loop.robots if n != mapper]
            goal = explorer.pivot(view, before, after, loop.pose(mapper), others, failed)
            if goal is None:
                break
        if not loop.go(mapper, goal.pose, goal.path):
            failed.append(goal.pose)
            goal = None
            continue
        explorer.taken.append(goal.pose)
        seen = loop.dwell(phase="mapping", reference=reference, mapper=mapper,
                          step=len(loop.steps))  # fmt: skip
        loop.steps.append(StepSpec(reference=reference, at=at, mapper=mapper,
                                   scans=[as_spec(goal.pose)]))  # fmt: skip
        loop.fleet.log("roles", reference=reference, mapper=mapper, step=len(loop.steps))
        loop.pivots += 1
        at = None
        if seen:
            return True, at
        failed.append(goal.pose)
        loop.retries.append(
            f"{mapper}{loop.index[mapper]} pivot of {reference}{loop.index[reference]}"
        )
        goal = None
    return False, at
