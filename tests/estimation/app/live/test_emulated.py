"""A simulated robot's LMS 200 read off a pty by the real driver: the same bytes, the same
stamps as the simulator's, cut into reads as the line delivers them."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from estimation.app.live.agent import SimulatedRobot
from estimation.app.live.emulated import SteppedClock
from estimation.app.mission.simulated import simulated_fleet
from estimation.app.resources import resolve_builtin
from estimation.app.sim.simulate import load_simulated
from sensors.errors import DeviceError

SPEC, CONFIG, WORLD, SPACE, SEED = load_simulated(
    resolve_builtin("missions", Path("essex_lab")), None, None
)


def test_a_dwell_through_the_pty_is_the_simulators_dwell() -> None:
    direct = SimulatedRobot(simulated_fleet(SPEC, CONFIG, WORLD, SEED, SPACE), "b")
    emulated = SimulatedRobot(simulated_fleet(SPEC, CONFIG, WORLD, SEED, SPACE), "b",
                              emulate=CONFIG)  # fmt: skip
    emulated.start_sensors()
    try:
        assert emulated.lms is not None
        assert emulated.lms.info.baud_rate == CONFIG.serial.baud_rate  # switched up from 9600
        for robot in (direct, emulated):
            robot.apply("dwell", {"fields": {}})
        sent, _, _ = direct.recorded()
        read, _, _ = emulated.recorded()
        lms = emulated.lms
        deadline = time.monotonic() + 5.0
        while lms.scans_read < len(sent) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert lms.scans_read == len(sent)  # the driver decoded every telegram it read
    finally:
        emulated.close()
    assert b"".join(d for _, d in read) == b"".join(d for _, d in sent)
    assert len(read) >= len(sent) > 300
    # every read ends a telegram's bytes or part of them, stamped with that telegram's stamp
    stamps = {t for t, _ in sent}
    assert {t for t, _ in read} <= stamps


def test_the_stepped_clock() -> None:
    clock = SteppedClock(-10.0)
    with pytest.raises(DeviceError, match="runs with wall time"):
        clock.set(5.0)
    assert -10.0 <= clock.now() < -9.0
    clock.hold()
    clock.set(3.0)
    clock.set(2.0)  # never backwards
    assert clock.now() == 3.0
