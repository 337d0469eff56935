"""Decoding a robot's capture: implausible scans are dropped and counted by reason."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from estimation.app.dataset import decode_robot
from sensors.errors import SensorError
from sensors.lms200.capture import CaptureWriter
from sensors.lms200.protocol.plausibility import ScanLimits
from sensors.lms200.protocol.scan import encode_scan, scan_interval_s
from sensors.lms200.protocol.telegram import TURN_S

LIMITS = ScanLimits.for_variant(100, 1.0, unit_mm=True, baud_rate=38400)


def write_capture(path: Path, baud_rate: int, corrupt: dict[int, dict[str, object]]) -> Path:
    """200 telegrams of continuous output at ``baud_rate``; ``corrupt`` replaces the encoder's
    arguments of some (each still has a valid checksum)."""
    turns = round(scan_interval_s(baud_rate, 101, 1.0, True) / TURN_S)
    with CaptureWriter(path, {"baud_rate": baud_rate}) as writer:
        for k in range(200):
            turn = 500 + turns * k
            options: dict[str, object] = {"scan_index": turn & 0xFF, "telegram_index": k & 0xFF}
            options.update(corrupt.get(k, {}))
            data = encode_scan(np.full(101, 3.0), **options)  # type: ignore[arg-type]
            writer.write((turn + 1) * TURN_S + len(data) * 10 / baud_rate + 0.002, data)
    return path


def test_implausible_scans_are_dropped_and_counted(tmp_path: Path) -> None:
    corrupt = {50: {"scan_index": 3}, 120: {"unit_mm": False}, 121: {"status": 0x17}}
    capture = write_capture(tmp_path / "a.cap", 38400, corrupt)
    stream = decode_robot(capture, 1, LIMITS)
    assert len(stream.scans) == 197
    assert stream.implausible == {"sequence": 1, "unit": 1, "status": 1}
    assert stream.implausible_scans == 3
    assert stream.telegrams == 200
    steps = np.diff(stream.times_s) / TURN_S
    assert set(np.round(steps).astype(int)) == {6, 12, 18}  # the gaps left by the three
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    unchecked = decode_robot(capture, 1)
    assert (len(unchecked.scans), unchecked.implausible) == (200, {})
    # Unchecked, the one bad scan index shifts every later scan by 256 turns (3.4 s).
    span = unchecked.times_s[-1] - unchecked.times_s[0]
    assert span == pytest.approx(stream.times_s[-1] - stream.times_s[0] + 256 * TURN_S, abs=1e-6)


def test_the_capture_header_sets_the_telegram_interval(tmp_path: Path) -> None:
    """Recorded at 500 kBd a telegram leaves every turn; the configured 38 400 Bd is overruled."""
    capture = write_capture(tmp_path / "fast.cap", 500000, {})
    stream = decode_robot(capture, 1, LIMITS)
    assert (len(stream.scans), stream.implausible_scans) == (200, 0)


def test_a_capture_of_another_variant_is_a_clear_error(tmp_path: Path) -> None:
    capture = write_capture(tmp_path / "a.cap", 38400, {})
    other = ScanLimits.for_variant(180, 1.0, unit_mm=True, baud_rate=38400)
    with pytest.raises(SensorError, match=r"all 200 scans are implausible .*\(200 count\)"):
        decode_robot(capture, 1, other)
