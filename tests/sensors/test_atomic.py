"""Atomic writes never leave a half-written file where the old one was."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from sensors.atomic import (
    MARKER,
    atomic_path,
    check_replaceable,
    output_kind,
    replace_directory,
    write_text_atomic,
)
from sensors.errors import OutputError


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


def _write(out: Path, kind: str, name: str) -> None:
    with replace_directory(out, kind) as work:
        (work / name).write_text(name)


def test_only_an_earlier_output_of_the_same_kind_is_replaced(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    _write(out, "dataset", "first.txt")
    assert output_kind(out) == "dataset"
    _write(out, "dataset", "second.txt")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "second.txt"]
    with pytest.raises(
        OutputError, match=r"holds a coopmap dataset; refusing to replace it with a result"
    ):
        _write(out, "result", "r.txt")
    assert (out / "second.txt").read_text() == "second.txt"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]  # no temporary left behind


def test_a_users_folder_is_never_replaced(tmp_path: Path) -> None:
    thesis = tmp_path / "my_thesis"
    thesis.mkdir()
    (thesis / "chapter1.tex").write_text("precious")
    with pytest.raises(OutputError, match=r"holds files coopmap did not write \(chapter1\.tex\)"):
        _write(thesis, "dataset", "x")
    assert (thesis / "chapter1.tex").read_text() == "precious"
    (thesis / MARKER).write_text("{not json")  # a broken marker is not coopmap's
    with pytest.raises(OutputError, match="did not write"):
        check_replaceable(thesis, "dataset")


@pytest.mark.parametrize("case", ["file", "symlink", "cwd", "parent"])
def test_files_links_and_the_working_folder_are_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, case: str
) -> None:
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    target = {"file": tmp_path / "f.txt", "symlink": tmp_path / "link", "cwd": Path("."),
              "parent": Path("..")}[case]  # fmt: skip
    if case == "file":
        target.write_text("keep")
    if case == "symlink":
        _write(tmp_path / "real", "result", "r")
        target.symlink_to(tmp_path / "real")
    expected = {"file": "is not a folder", "symlink": "symbolic link",
                "cwd": "working folder", "parent": "working folder"}[case]  # fmt: skip
    with pytest.raises(OutputError, match=expected):
        _write(target, "result", "x")
    if case == "file":
        assert target.read_text() == "keep"


def test_an_empty_folder_may_be_used(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    _write(tmp_path / "empty", "result", "r.txt")
    assert (tmp_path / "empty" / "r.txt").is_file()


def test_outputs_are_readable_by_others_as_the_umask_allows(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        _write(tmp_path / "out", "result", "r.txt")
        write_text_atomic(tmp_path / "out" / "f.txt", "x")
    finally:
        os.umask(old)
    assert (tmp_path / "out").stat().st_mode & 0o777 == 0o755
    assert (tmp_path / "out" / "f.txt").stat().st_mode & 0o777 == 0o644


def test_a_killed_runs_hidden_folder_is_removed_by_the_next_run(tmp_path: Path) -> None:
    import json
    import subprocess
    import sys

    out = tmp_path / "result"
    code = (
        "import os, sys\n"
        "from pathlib import Path\n"
        "from sensors.atomic import replace_directory\n"
        "with replace_directory(Path(sys.argv[1]), 'result') as work:\n"
        "    (work / 'half.txt').write_text('x')\n"
        "    os._exit(9)\n"  # killed half-way: no clean-up runs
    )
    subprocess.run([sys.executable, "-c", code, str(out)], check=False, timeout=60)
    left = [p for p in tmp_path.iterdir() if p.name.startswith(".result.")]
    assert len(left) == 1
    assert (left[0] / "half.txt").is_file()
    alive = tmp_path / ".result.running"
    alive.mkdir()
    (alive / MARKER).write_text(json.dumps({"kind": "result", "pid": os.getpid()}))
    foreign = tmp_path / ".result.mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("not coopmap's")
    _write(out, "result", "r.txt")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == [".result.mine", ".result.running", "result"]  # a live run's and a user's stay


def test_a_full_disk_names_the_file_being_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import errno

    def full(self: Path, *args: object, **kwargs: object) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full)
    target = tmp_path / "report.json"
    with pytest.raises(OSError, match="No space left on device") as caught:
        write_text_atomic(target, "x")
    assert caught.value.filename == str(target)
    assert list(tmp_path.iterdir()) == []  # no temporary left behind
