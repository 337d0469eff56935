"""Atomic writes never leave a half-written file where the old one was."""

from __future__ import annotations

from pathlib import Path

import pytest

from sensors.atomic import atomic_path, write_text_atomic


def test_success_replaces_the_file_and_leaves_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "out.txt"
    write_text_atomic(path, "first")
    write_text_atomic(path, "second")
    assert path.read_text() == "second"
    assert [p.name for p in path.parent.iterdir()] == ["out.txt"]


def test_failure_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "map.npz"
    path.write_bytes(b"old map")
    seen: list[Path] = []

    def crash_while_writing() -> None:
        with atomic_path(path) as tmp:
            seen.append(tmp)
            tmp.write_bytes(b"half a new m")
            raise RuntimeError("crash while writing")

    with pytest.raises(RuntimeError, match="crash"):
        crash_while_writing()
    assert seen[0].suffix == ".npz"
    assert seen[0].parent == tmp_path
    assert path.read_bytes() == b"old map"
    assert [p.name for p in tmp_path.iterdir()] == ["map.npz"]
