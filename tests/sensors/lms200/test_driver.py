"""The driver against the device emulator over a real pseudo-terminal."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from sensors.errors import DeviceError
from sensors.lms200.driver import Lms200
from sensors.lms200.emulator import Lms200Emulator
from sensors.lms200.protocol.commands import cmd_mode, cmd_request_type
from sensors.lms200.protocol.stream import StreamParser, Telegram
from sensors.lms200.protocol.telegram import ProtocolError


def ramp(t_s: float, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Ranges that encode the sample index and time; flags on every tenth sample."""
    ranges = 1.0 + 0.01 * np.arange(count) + 0.001 * (round(t_s * 10) % 10)
    flags = np.where(np.arange(count) % 10 == 0, 7, 0)
    return ranges, flags


@pytest.fixture
def emulator() -> Iterator[Lms200Emulator]:
    with Lms200Emulator(ramp, power_on_baud=9600) as emu:
        yield emu


def fast_driver(port: str, **kwargs: object) -> Lms200:
    options: dict[str, object] = {
        "ack_timeout_s": 0.1, "reply_timeout_s": 0.5, "baud_switch_wait_s": 0.02,
        "stream_timeout_s": 0.5,
    }  # fmt: skip
    options.update(kwargs)
    return Lms200(port, **options)  # type: ignore[arg-type]


def test_start_up_and_streaming(emulator: Lms200Emulator) -> None:
    driver = fast_driver(emulator.device_path, baud_rate=38400)
    info = driver.start()
    assert info.found_baud == 9600
    assert info.baud_rate == 38400
    assert info.type_text == "LMS200;301063;V02.10"
    assert info.config_written
    assert (info.angle_deg, info.resolution_deg, info.measuring_mode) == (100, 1.0, 1)
    state = emulator.state
    assert (state.baud_rate, state.angle_deg, state.resolution_deg) == (38400, 100, 1.0)
    assert state.config.measuring_mode == 1
    assert state.config.realtime_indices
    scans = list(driver.scans(limit=13))
    assert len(scans) == 13
    stamps = np.array([s.stamp_s for s in scans])
    indices = np.array([s.scan_index for s in scans])
    # 38 400 Bd, 101 values: one scan every 6 turns. Like the sensor, the emulator drops a scan
    # that falls due while the line still sends the one before (§8): on a loaded machine its
    # thread can run late by that much, once in a while.
    gaps = np.diff(indices) % 256
    assert set(gaps) <= {6, 12}
    assert np.count_nonzero(gaps == 6) >= len(gaps) - 2
    rate = (gaps.sum() / 6) / (stamps[-1] - stamps[0])  # scans due per second
    assert rate == pytest.approx(12.5, rel=0.08)
    first = scans[0]
    np.testing.assert_allclose(
        first.ranges_m[:5] - first.ranges_m[0], [0.0, 0.01, 0.02, 0.03, 0.04], atol=1e-9
    )
    assert first.reflector[::10].all()
    assert not first.reflector[1:10].any()
    driver.stop()
    assert not emulator.state.streaming
    driver.close()


def test_second_start_finds_the_rate_and_does_not_rewrite_eeprom(emulator: Lms200Emulator) -> None:
    with fast_driver(emulator.device_path, baud_rate=38400) as driver:
        driver.start()
    commands_after_first = emulator.state.commands
    with fast_driver(emulator.device_path, baud_rate=38400) as driver:
        info = driver.start()
        assert info.found_baud == 38400
        assert not info.config_written
        assert len(list(driver.scans(limit=2))) == 2
    assert emulator.state.commands > commands_after_first
    assert not emulator.state.streaming  # close() ended the stream


def test_finds_a_sensor_at_an_unexpected_rate() -> None:
    with Lms200Emulator(ramp, power_on_baud=19200) as emu, fast_driver(emu.device_path) as driver:
        driver.baud_rate = 9600
        info = driver.start()
        assert info.found_baud == 19200
        assert emu.state.baud_rate == 9600
        assert len(list(driver.scans(limit=2))) == 2


def test_naks_are_retried(emulator: Lms200Emulator) -> None:
    emulator.nak_next = 2
    with fast_driver(emulator.device_path, baud_rate=9600) as driver:
        driver.start()
    assert emulator.state.naks_sent == 2


def test_persistent_naks_are_a_clear_error(emulator: Lms200Emulator) -> None:
    driver = fast_driver(emulator.device_path, baud_rate=9600, retries=2)
    driver.open()
    driver.detect_baud()
    emulator.nak_next = 3
    with pytest.raises(
        DeviceError, match=r"the sensor NAKed it while reading the type \(3 tries at 9600 Bd\)"
    ):
        driver._transact(cmd_request_type(), 0xBA, "reading the type", 0.5)
    emulator.nak_next = 10
    with pytest.raises(
        DeviceError, match=r"the sensor NAKed it while probing the baud rate \(3 tries at 9600 Bd\)"
    ):
        driver.start()
    driver.close()


def test_silent_sensor(emulator: Lms200Emulator) -> None:
    emulator.mute()
    driver = fast_driver(emulator.device_path, baud_rate=38400)
    with pytest.raises(
        DeviceError, match=r"no LMS answered at any of \[38400, 9600, 19200, 500000\] Bd"
    ):
        driver.start()
    driver.close()


def test_sensor_that_stops_talking_while_streaming(emulator: Lms200Emulator) -> None:
    driver = fast_driver(emulator.device_path, baud_rate=38400)
    driver.start()
    scans = driver.scans()
    next(scans)
    emulator.mute()
    with pytest.raises(
        DeviceError,
        match=r"no scan for 0\.\d s while streaming at 38400 Bd: the sensor stopped talking",
    ):
        for _ in scans:
            pass
    driver.close()


def test_device_that_disappears_while_streaming(emulator: Lms200Emulator) -> None:
    driver = fast_driver(emulator.device_path, baud_rate=38400)
    driver.start()
    scans = driver.scans()
    next(scans)
    threading.Timer(0.1, emulator.disconnect).start()
    with pytest.raises(DeviceError, match=r"(disappeared while streaming scans|stopped talking)"):
        for _ in scans:
            pass
    driver.close()


def test_wrong_password_is_reported(emulator: Lms200Emulator) -> None:
    driver = fast_driver(emulator.device_path, baud_rate=9600, password="WRONG_PW")
    with pytest.raises(
        DeviceError, match="mode switch refused while entering installation mode: wrong password"
    ):
        driver.start()
    driver.close()


def test_refused_command_and_unopenable_ports(emulator: Lms200Emulator) -> None:
    driver = fast_driver(emulator.device_path, baud_rate=9600)
    driver.open()
    driver.detect_baud()
    with pytest.raises(
        DeviceError, match=r"refused the command while entering diagnostics \(reply 92"
    ):
        driver._mode(cmd_mode(0x10), "entering diagnostics")
    driver.close()
    with pytest.raises(DeviceError, match="cannot open /dev/nonexistent-lms"):
        Lms200("/dev/nonexistent-lms").open()
    with pytest.raises(DeviceError, match="baud rate must be one of"):
        Lms200("loop://", baud_rate=115200)
    with pytest.raises(ProtocolError, match="no LMS 200 variant"):
        Lms200("loop://", angle_deg=180, resolution_deg=0.25)
    with pytest.raises(DeviceError, match="not streaming; call start"):
        next(Lms200("loop://").scans())


def test_loopback_url_hears_no_sensor() -> None:
    driver = fast_driver("loop://", baud_rate=38400, ack_timeout_s=0.05)
    start = time.monotonic()
    with pytest.raises(DeviceError, match="no LMS answered"):
        driver.start()
    assert time.monotonic() - start < 2.0
    driver.close()


def test_tap_sees_every_byte(emulator: Lms200Emulator) -> None:
    seen = bytearray()
    driver = fast_driver(emulator.device_path, baud_rate=38400, tap=lambda _t, b: seen.extend(b))
    driver.start()
    list(driver.scans(limit=3))
    driver.stop()
    driver.close()
    parser = StreamParser()
    telegrams = [e for e in parser.feed(bytes(seen)) if isinstance(e, Telegram)]
    assert sum(t.code == 0xB0 for t in telegrams) >= 3
    assert {0xA0, 0xBA, 0xB1, 0xF4} <= {t.code for t in telegrams}


def test_closing_against_a_sensor_that_naks_everything_is_quick(emulator: Lms200Emulator) -> None:
    """A NAK is the sensor's answer even when a stray 06 byte of the stream came first."""
    driver = Lms200(emulator.device_path, baud_rate=38400)  # the default timeouts
    driver.start()
    list(driver.scans(limit=3))
    emulator.nak_next = 1000
    started = time.monotonic()
    driver.close()
    assert time.monotonic() - started < 1.5
    assert emulator.state.naks_sent >= 3  # every try was NAKed and retried


def test_a_nak_after_a_stray_ack_byte_is_a_nak() -> None:
    """06 then 15 before the reply: the 06 was stray (the sensor answers once), the NAK counts."""
    driver = fast_driver("loop://")
    driver.open(9600)
    try:
        driver._port.write(b"\x06\x15")
        started = time.monotonic()
        assert driver._await(0xA0, "testing", timeout_s=2.0) == "nak"
        assert time.monotonic() - started < 0.5
    finally:
        driver.close()
