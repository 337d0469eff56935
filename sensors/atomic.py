"""Atomic file writes: a crash never leaves a half-written file where the old one was."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from sensors.errors import OutputError

__all__ = [
    "MARKER",
    "atomic_path",
    "check_replaceable",
    "output_kind",
    "remove_leftovers",
    "replace_directory",
    "write_bytes_atomic",
    "write_text_atomic",
]


@contextlib.contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path`` in one rename.

    On an exception the temporary file is removed and ``path`` is left as it was. The temporary
    name keeps ``path``'s suffix, so writers that choose a format by suffix still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent
    )
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it private; outputs are shared
        os.replace(tmp, path)
    except OSError as exc:
        if exc.filename is not None and Path(exc.filename) != tmp:
            raise
        # A full disk fails on the temporary file: name the file the user asked for.
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def write_bytes_atomic(path: Path | str, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: Path | str, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


#: The file that marks a folder as coopmap's own output, and of which kind.
MARKER = ".coopmap"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _marker(folder: Path) -> dict[str, object]:
    marker = Path(folder) / MARKER
    try:
        if marker.is_symlink() or not marker.is_file() or marker.stat().st_size > 4096:
            return {}
        document = json.loads(marker.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}
    return document if isinstance(document, dict) else {}


def output_kind(folder: Path) -> str | None:
    """The kind of coopmap output ``folder`` holds ("dataset", "result", …), from its marker."""
    kind = _marker(folder).get("kind")
    return kind if isinstance(kind, str) else None


def _alive(pid: object) -> bool:
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # it exists, owned by someone else
    return True


def remove_leftovers(out_dir: Path, kind: str) -> list[Path]:
    """Remove the hidden folders that runs writing ``out_dir`` left behind when they were killed
    (``.<name>.*`` beside it, marked as this ``kind`` by a process that is gone); returns them."""
    out_dir = Path(out_dir)
    removed: list[Path] = []
    if not out_dir.parent.is_dir():
        return removed
    for candidate in out_dir.parent.glob(f".{out_dir.name}.*"):
        if candidate.is_symlink() or not candidate.is_dir():
            continue
        marker = _marker(candidate)
        if marker.get("kind") == kind and not _alive(marker.get("pid")):
            shutil.rmtree(candidate, ignore_errors=True)
            removed.append(candidate)
    return removed


def check_replaceable(out_dir: Path, kind: str) -> None:
    """Refuse an output folder that holds anything coopmap did not write as a ``kind``.

    Allowed: a path that does not exist, an empty folder, or a folder marked as an earlier
    coopmap ``kind``. Refused (``OutputError``): the working folder or one of its parents, a
    file, a symbolic link, a user's folder, a coopmap output of another kind (a dataset as a
    result's ``--out``).
    """
    out_dir = Path(out_dir)
    resolved = out_dir.resolve()
    here = Path.cwd().resolve()
    if resolved == here or resolved in here.parents:
        raise OutputError(f"{out_dir}: refusing to write into the working folder or its parent")
    if out_dir.is_symlink():
        raise OutputError(f"{out_dir}: is a symbolic link; refusing to replace it")
    if not out_dir.exists():
        return
    if not out_dir.is_dir():
        raise OutputError(f"{out_dir}: exists and is not a folder; refusing to replace it")
    found = output_kind(out_dir)
    if found == kind:
        return
    if found is not None:
        raise OutputError(
            f"{out_dir}: holds a coopmap {found}; refusing to replace it with a {kind}"
        )
    entries = sorted(p.name for p in out_dir.iterdir())
    if entries:
        shown = ", ".join(entries[:3]) + (", …" if len(entries) > 3 else "")
        raise OutputError(
            f"{out_dir}: holds files coopmap did not write ({shown}); refusing to replace it "
            "(choose another output folder)"
        )


@contextlib.contextmanager
def replace_directory(out_dir: Path, kind: str) -> Iterator[Path]:
    """Yield a fresh folder beside ``out_dir``, marked as a coopmap ``kind``; on success it takes
    ``out_dir``'s place in one rename. ``out_dir`` must pass :func:`check_replaceable`: only an
    earlier coopmap output of the same kind is ever replaced, and never on failure."""
    out_dir = Path(out_dir)
    check_replaceable(out_dir, kind)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    remove_leftovers(out_dir, kind)
    work = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        os.chmod(work, 0o777 & ~_umask())  # mkdtemp makes it private; outputs are shared
        marker = {"kind": kind, "pid": os.getpid()}  # the pid tells a killed run's leftovers
        (work / MARKER).write_text(json.dumps(marker) + "\n", encoding="utf-8")
        yield work
        check_replaceable(out_dir, kind)  # nothing else moved in while we wrote
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    old = None
    if out_dir.exists():
        old = out_dir.with_name(f".{out_dir.name}.old-{work.name.rsplit('.', 1)[-1]}")
        out_dir.rename(old)
    work.rename(out_dir)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
