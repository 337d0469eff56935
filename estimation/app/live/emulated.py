"""A simulated robot's LMS 200 on a pseudo-terminal: the agent's ``--emulate`` mode.

The simulator's telegrams do not go straight into the capture: the device emulator
(``sensors.lms200.emulator``) sends them on a pty, and the real driver (``Lms200``, pyserial)
reads them there — the power-on message, the baud-rate switch and the mode switches first, as
on a robot — and its tap writes what it reads, stamped on arrival, as the capture's records.

Both sides run on one stepped clock: it runs with wall time while the driver sets the sensor
up, then stands still and is set by the agent to each telegram's receive stamp, after the
driver has read the one before. So a telegram arrives stamped with the simulator's receive
stamp whatever the machine's load, and the mission runs as fast as the pty carries it; the
bytes are cut into reads as the line delivers them.
"""

from __future__ import annotations

import threading
import time
from collections import deque

import numpy as np

from estimation.app.config import Config
from estimation.app.rig import driver_from_config
from sensors.errors import DeviceError
from sensors.lms200.emulator import Lms200Emulator

__all__ = ["EmulatedLms", "SteppedClock"]

#: How long the driver may take to read one telegram before the link counts as broken (s).
_READ_TIMEOUT_S = 10.0
#: How far before the first telegram the clock starts, while the driver sets the sensor up.
_SETUP_S = 60.0


class SteppedClock:
    """Wall time from ``start_s`` until :meth:`hold`; then only what :meth:`set` says."""

    def __init__(self, start_s: float) -> None:
        self._start, self._m0 = start_s, time.monotonic()
        self._held: float | None = None

    def now(self) -> float:
        held = self._held
        return self._start + (time.monotonic() - self._m0) if held is None else held

    def hold(self) -> None:
        self._held = self.now()

    def set(self, t_s: float) -> None:
        if self._held is None:
            raise DeviceError("the clock runs with wall time until it is held")
        self._held = max(self._held, t_s)


def _no_scan(t_s: float, count: int) -> tuple[np.ndarray, np.ndarray]:
    return np.full(count, np.nan), np.zeros(count, dtype=bool)


class EmulatedLms:
    """The emulator, the driver reading it, and the telegrams passed from one to the other."""

    def __init__(self, config: Config, now_s: float) -> None:
        self.baud_rate = config.serial.baud_rate
        self.clock = SteppedClock(now_s - _SETUP_S)
        self._queue: deque[tuple[float, bytes]] = deque()
        self._taps: list[tuple[float, bytes]] = []
        self._read = 0
        self._lock = threading.Condition()
        self.emulator = Lms200Emulator(_no_scan, clock=self.clock.now, stream=self._next)
        port = self.emulator.start()
        self.driver = driver_from_config(config, port, stream_timeout_s=1e9)
        self.driver.tap = self._tap
        self.driver.clock = self.clock.now
        try:
            self.driver.open()
            self.info = self.driver.start()
        except BaseException:
            self.close()
            raise
        self.clock.hold()
        with self._lock:
            self._taps.clear()  # the set-up's replies are not the mission's capture
            self._read = 0
        self._error: BaseException | None = None
        self.scans_read = 0
        self._reader = threading.Thread(target=self._run, name="lms-driver", daemon=True)
        self._reader.start()

    def _next(self, after_s: float) -> tuple[float, bytes] | None:
        with self._lock:
            return self._queue.popleft() if self._queue else None

    def _tap(self, stamp_s: float, chunk: bytes) -> None:
        with self._lock:
            self._taps.append((stamp_s, chunk))
            self._read += len(chunk)
            self._lock.notify_all()

    def _run(self) -> None:
        """Read the stream as a recorder does: the driver's tap takes every byte; the scans
        the driver decodes are counted (its plausibility rules dropped the others)."""
        try:
            for _ in self.driver.scans():
                self.scans_read += 1
        except BaseException as exc:  # the agent reports it at the next telegram
            self._error = exc

    def pass_through(self, records: list[tuple[float, bytes]]) -> list[tuple[float, bytes]]:
        """Send ``records`` (the simulator's receive stamps and telegrams) through the pty;
        the capture records the driver's tap wrote meanwhile."""
        if not records:
            return []
        byte_s = 10.0 / self.baud_rate
        with self._lock:
            expected = self._read
            self._queue.extend(
                (stamp - len(data) * byte_s - 0.002, data) for stamp, data in records
            )
        self.emulator.stream_more()
        for stamp, data in records:
            expected += len(data)
            self.clock.set(stamp)
            deadline = time.monotonic() + _READ_TIMEOUT_S
            with self._lock:
                while self._read < expected:
                    if self._error is not None:
                        raise DeviceError(f"LMS driver on {self.driver.port}: {self._error}")
                    if not self._lock.wait(max(0.0, deadline - time.monotonic())):
                        raise DeviceError(
                            f"LMS emulator on {self.driver.port}: a telegram did not arrive "
                            f"within {_READ_TIMEOUT_S:g} s"
                        )
        with self._lock:
            taps, self._taps = self._taps, []
        return taps

    def close(self) -> None:
        self.emulator.close()
        self.driver.streaming = False
        self.driver.close()
