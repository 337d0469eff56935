"""Building a robot's recorder from the configuration and the command's options."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from estimation.app.config import Config
from estimation.app.record import RecordOptions, build_recorder, prompt_lines
from sensors.errors import RecordingError


def test_the_recorder_gets_the_driver_the_configuration_describes(tmp_path: Path) -> None:
    config = Config.model_validate({"serial": {"baud_rate": 19200}})
    recorder = build_recorder(
        config,
        RecordOptions(
            "a", tmp_path / "r", lms_port="/dev/ttyX", clock_offset_s=0.0, robots=("a", "b")
        ),
    )
    assert recorder.operator.robots == ["a", "b"]
    lms = recorder._lms_device
    assert lms is not None
    assert (lms.port, lms.baud_rate) == ("/dev/ttyX", 19200)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"robot": "A"}, "one lowercase letter"),
        ({"robots": ("a", "bb")}, "--robots: names are one lowercase letter"),
        ({"clock_offset_s": None}, "give --clock-server"),
        ({"sync_interval_s": 0.0}, "--sync-interval must be > 0"),
        ({"odometry": "ftp://x"}, "expected tcp://"),
    ],
)
def test_bad_options_are_errors(tmp_path: Path, options: dict[str, object], message: str) -> None:
    base: dict[str, object] = {"robot": "a", "out_dir": tmp_path / "r", "clock_offset_s": 0.0}
    with pytest.raises(RecordingError, match=message):
        build_recorder(Config(), RecordOptions(**{**base, **options}))  # type: ignore[arg-type]


def test_prompt_lines_end_with_none() -> None:
    lines = prompt_lines(io.StringIO("start\n  dwell  \n"))
    assert [lines.get(timeout=2), lines.get(timeout=2), lines.get(timeout=2)] == [
        "start", "dwell", None,
    ]  # fmt: skip
