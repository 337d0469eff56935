"""A simulated mission flown by the mission loop (``plan: auto`` with ``auto.planner: map``).

The simulator's robots (:class:`~estimation.app.mission.fleet.SimulatedFleet`) move through the
true world; the loop sees only what they record and plans on its estimated map. The dataset is
written into ``work`` as the mission goes, and the result into ``work/result``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from estimation.app.config import Config, ConfigError
from estimation.app.mission.fleet import SimulatedFleet
from estimation.app.mission.loop import LoopResult, MissionLoop
from estimation.errors import EstimationError
from mapping.errors import MapError
from sensors.errors import SensorError
from sensors.sim.mission import MissionError, MissionSpec
from sensors.sim.planner import FreeSpace, free_space
from sensors.sim.world import World

__all__ = ["MISSION_FAILURES", "PartialMissionError", "fly", "mission_starts", "simulated_fleet"]

#: The errors that end a mission as coopmap's known failures (not a bug in it): a station the
#: estimator cannot take, a collision, a goal the fleet refuses.
MISSION_FAILURES: tuple[type[Exception], ...] = (SensorError, EstimationError, MapError,
                                                 ConfigError)  # fmt: skip


class PartialMissionError(MissionError):
    """The mission failed once it was under way; the dataset holds its recording up to the
    failure (``partial.json``)."""


def mission_starts(mission: MissionSpec) -> dict[str, np.ndarray]:
    """The robots' declared start poses (x_m, y_m, yaw_rad): the map frame."""
    return {r.name: np.array([r.start[0], r.start[1], math.radians(r.start[2])])
            for r in mission.robots}  # fmt: skip


def simulated_fleet(mission: MissionSpec, config: Config, world: World, seed: int,
                    space: FreeSpace) -> SimulatedFleet:  # fmt: skip
    """The mission's robots in the simulator. ``space`` is the planning free space (with its
    margin): a robot that does not start in it is refused; the bodies collide only when they
    touch."""
    starts = mission_starts(mission)
    body_space = free_space(world, robot_radius_m=config.robot.footprint_radius_m,
                            robot_height_m=config.robot.body_height_m, margin_m=0.0)  # fmt: skip
    for name, pose in starts.items():
        if not space.is_free(pose[:2]):
            raise MissionError(f"robot {name!r} starts at ({pose[0]:g}, {pose[1]:g}), where it "
                               "does not fit")  # fmt: skip
    return SimulatedFleet(world, body_space, config, starts, seed)


def fly(
    mission: MissionSpec,
    config: Config,
    world: World,
    space: FreeSpace,
    seed: int,
    work: Path,
    *,
    final: Path | None = None,
    concurrent: bool = True,
    status: Callable[[str], None] | None = None,
    observe: Callable[[Any], None] | None = None,
) -> LoopResult:
    """Fly ``mission`` in the simulator with the loop; the dataset and result go to ``work``
    (which becomes ``final`` when the caller replaces it there). ``observe`` is the loop's
    hook after every dwell (:attr:`MissionLoop.observe`). A known failure once under way
    (:data:`MISSION_FAILURES`) closes the dataset as far as it was recorded and raises
    :class:`PartialMissionError`; anything else discards it."""
    fleet = simulated_fleet(mission, config, world, seed, space)
    loop = MissionLoop(
        fleet, mission, config, work, concurrent=concurrent, progress=status, observe=observe
    )
    try:
        reason = loop.run()
    except MISSION_FAILURES as exc:
        failure = " ".join(str(exc).split()) or type(exc).__name__
        try:
            loop.keep(failure)
        except BaseException:
            loop.discard()
            fleet.close()
            raise exc from None
        fleet.close()
        raise PartialMissionError(failure) from exc
    except BaseException:
        loop.discard()
        fleet.close()
        raise
    fleet.close()
    return loop.finish(work / "result", reason, final)
