"""The recording folder: created fresh and marked, read back with its partial files."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sensors.errors import OutputError
from sensors.recording.folder import create_folder, unix_pair


def test_a_new_folder_is_marked_as_a_recording(tmp_path: Path) -> None:
    create_folder(tmp_path / "rec")
    assert json.loads((tmp_path / "rec" / ".coopmap").read_text()) == {"kind": "recording"}
    with pytest.raises(OutputError, match="recordings are never replaced"):
        create_folder(tmp_path / "rec")
    (tmp_path / "empty").mkdir()
    create_folder(tmp_path / "empty")


def test_a_file_is_not_a_recording_folder(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputError, match="not a folder"):
        create_folder(tmp_path / "f")


def test_unix_pairs_relate_the_clocks() -> None:
    import time

    monotonic, unix = unix_pair()
    assert abs((time.time() - time.monotonic()) - (unix - monotonic)) < 0.01
