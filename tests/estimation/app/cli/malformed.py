"""Shared machinery of the malformed-input suites (``test_malformed_*.py``, ``test_output_safety``).

A :class:`Case` is one damaged input: its family, what is damaged, the command line (with the
placeholders ``{ds}`` — a fresh copy of the module's simulated dataset —, ``{tmp}`` — the case's
own folder — and ``{repo}``), and the expected outcome: a one-line ``coopmap: error: `` matching
``error``, or success with ``ok`` matching stdout. Commands run in-process (typer's CliRunner)
under a hard timeout (SIGALRM, which also interrupts a read blocked on a FIFO), so a hang fails
the case instead of blocking the suite; inputs that could fill memory (devices) run in a
subprocess with an address-space limit. Bomb cases measure their peak with tracemalloc.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tracemalloc
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any
from unittest import mock

import pytest
from typer.testing import CliRunner

from tests.estimation.app.missions import copy_of
from tests.paths import REPO

#: Every case must finish within this (seconds); a slower one is a hang.
CASE_TIMEOUT_S = 20
#: Peak Python/numpy memory a bomb case may use (tracemalloc), bytes.
BOMB_PEAK_LIMIT = 400 * 2**20
#: Address space of a guarded subprocess (devices such as /dev/zero), bytes.
GUARD_AS_LIMIT = 6 * 2**30
#: Peaks measured by bomb cases, by case id (the suite's report prints them).
PEAKS: dict[str, int] = {}


@dataclass(frozen=True)
class Workspace:
    """Where a case runs: its own folder and (when it uses one) a copy of the dataset."""

    tmp: Path
    ds: Path

    @property
    def result(self) -> Path:
        return self.ds / "result"

    def fields(self) -> dict[str, str]:
        return {"ds": str(self.ds), "tmp": str(self.tmp), "repo": str(REPO)}


Setup = Callable[[Workspace], None]
Check = Callable[[Workspace, "Outcome"], None]


@dataclass(frozen=True)
class Case:
    """One malformed input and what coopmap must make of it."""

    family: str
    damage: str
    args: tuple[str, ...]
    error: str | None = None  # regex of the one error line
    ok: str | None = None  # regex stdout must match on success
    problem: str | None = None  # regex of a report on stdout, exit 2 (dataset check)
    setup: tuple[Setup, ...] = ()
    check: Check | None = None
    keep: tuple[str, ...] = ()  # trees (relative to {tmp}) that must stay byte-identical
    bomb: bool = False  # measure the peak memory
    guarded: bool = False  # run in a subprocess with an address-space limit
    cwd: str | None = None  # working folder (a placeholder path)
    dataset: bool = False  # copy the dataset even when the command line does not name it

    @property
    def id(self) -> str:
        slug = re.sub(r"[^a-z0-9]+", "-", self.damage.lower()).strip("-")
        return f"{self.family}:{slug}"

    @property
    def uses_dataset(self) -> bool:
        return self.dataset or any("{ds}" in a for a in (*self.args, self.cwd or ""))

    def __post_init__(self) -> None:
        given = [self.error, self.ok, self.problem]
        assert sum(g is not None for g in given) == 1, self.damage


@dataclass(frozen=True)
class Outcome:
    code: int
    stdout: str
    stderr: str
    exception: BaseException | None = None
    traceback: str = ""


def simulated_dataset(
    factory: pytest.TempPathFactory, simulated: Path, *, result: bool = True
) -> Path:
    """The module's own copy of the session's essex_lab dataset (``simulated``), with a batch
    result when asked."""
    from estimation.app.pipeline import run_batch

    out = copy_of(simulated, factory, "mission")
    if result:
        run_batch(out)
    return out


def cases_param(cases: list[Case]) -> Any:
    """``pytest.mark.parametrize`` over cases, ids ``family:damage``; ids must be unique."""
    ids = [c.id for c in cases]
    assert len(ids) == len(set(ids)), sorted(i for i in ids if ids.count(i) > 1)
    return pytest.mark.parametrize("case", cases, ids=ids)


# --- damage ---------------------------------------------------------------------------------


def _target(ws: Workspace, rel: str) -> Path:
    path = Path(rel.format(**ws.fields()))
    return path if path.is_absolute() else ws.tmp / path


def _clear(path: Path) -> None:
    if path.is_symlink() or path.is_file() or path.is_fifo():
        path.unlink()
    elif path.is_dir():
        shutil.rmtree(path)


def write(rel: str, data: bytes | str | Callable[[], bytes | str]) -> Setup:
    """Replace the file at ``rel`` ({ds}/..., or relative to {tmp}) with ``data``."""

    def setup(ws: Workspace) -> None:
        path = _target(ws, rel)
        _clear(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        content = data() if callable(data) else data
        if isinstance(content, str):
            content = content.encode("utf-8")
        path.write_bytes(content)

    return setup


def edit(rel: str, change: Callable[[bytes], bytes]) -> Setup:
    """Rewrite the file at ``rel`` through ``change``."""

    def setup(ws: Workspace) -> None:
        path = _target(ws, rel)
        path.write_bytes(change(path.read_bytes()))

    return setup


def edit_text(rel: str, change: Callable[[str], str]) -> Setup:
    return edit(rel, lambda b: change(b.decode("utf-8")).encode("utf-8"))


def remove(rel: str) -> Setup:
    return lambda ws: _clear(_target(ws, rel))


def fifo(rel: str) -> Setup:
    def setup(ws: Workspace) -> None:
        path = _target(ws, rel)
        _clear(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        os.mkfifo(path)

    return setup


def directory(rel: str) -> Setup:
    def setup(ws: Workspace) -> None:
        path = _target(ws, rel)
        _clear(path)
        (path / "inside").mkdir(parents=True)

    return setup


def symlink(rel: str, target: str) -> Setup:
    def setup(ws: Workspace) -> None:
        path = _target(ws, rel)
        _clear(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.symlink_to(target.format(**ws.fields()))

    return setup


def copy(source: str, rel: str) -> Setup:
    def setup(ws: Workspace) -> None:
        src, dst = _target(ws, source), _target(ws, rel)
        _clear(dst)
        dst.parent.mkdir(parents=True, exist_ok=True)
        (shutil.copytree if src.is_dir() else shutil.copyfile)(src, dst)

    return setup


def json_lines(rel: str, change: Callable[[list[dict[str, Any]]], list[Any]]) -> Setup:
    """Rewrite a JSON-lines file through ``change`` on its decoded objects."""

    def rewrite(data: bytes) -> bytes:
        rows = [json.loads(line) for line in data.decode().splitlines() if line.strip()]
        return "".join(json.dumps(r) + "\n" for r in change(rows)).encode()

    return edit(rel, rewrite)


def json_file(rel: str, change: Callable[[Any], Any]) -> Setup:
    return edit(rel, lambda b: json.dumps(change(json.loads(b)), indent=1).encode())


# --- running --------------------------------------------------------------------------------


class Hang(BaseException):
    """A case ran past its timeout (not an ``Exception``, so no ``except Exception`` eats it)."""


@contextlib.contextmanager
def deadline(seconds: int) -> Iterator[None]:
    """Raise :class:`Hang` in the main thread after ``seconds``; a blocked ``open()`` or
    ``read()`` of a FIFO is interrupted too (PEP 475 retries only when the handler returns)."""

    def alarm(signum: int, frame: FrameType | None) -> None:
        raise Hang(f"no answer after {seconds} s")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def invoke(args: list[str], timeout_s: int = CASE_TIMEOUT_S) -> Outcome:
    """Run one command line in-process under a hard timeout."""
    import traceback

    import typer.testing

    try:
        # The click command is built once: typer builds it anew on every invoke (40 ms).
        with deadline(timeout_s), mock.patch.object(typer.testing, "_get_command", _command):
            result = CliRunner().invoke(app_(), args)
    except Hang as exc:
        return Outcome(-1, "", f"HANG: {exc}", exc)
    exc = result.exception
    text = ""
    if exc is not None and not isinstance(exc, SystemExit) and result.exc_info is not None:
        text = "".join(traceback.format_exception(*result.exc_info))
    return Outcome(result.exit_code, result.stdout, result.stderr, exc, text)


def app_() -> Any:
    from estimation.app.cli.main import app

    return app


@functools.cache
def _click_command() -> Any:
    import typer.main

    return typer.main.get_command(app_())


def _command(app: Any) -> Any:
    assert app is app_()
    return _click_command()


_GUARD_SCRIPT = """
import json, resource, signal, sys
resource.setrlimit(resource.RLIMIT_AS, ({limit}, {limit}))
from tests.estimation.app.cli.malformed import invoke
from tests.estimation.app.missions import copy_of
out = []
for args in json.loads(sys.stdin.read()):
    o = invoke(args, {timeout})
    out.append([o.code, o.stdout, o.stderr, o.traceback])
sys.stdout.write("\\n@@RESULT@@" + json.dumps(out))
"""


def invoke_guarded(
    commands: list[list[str]], cwd: Path | None = None, timeout_s: int = 20
) -> list[Outcome]:
    """Run command lines in one subprocess whose address space is limited (a device read whole
    fails there instead of filling the machine), each under its own timeout."""
    script = _GUARD_SCRIPT.format(limit=GUARD_AS_LIMIT, timeout=timeout_s)
    proc = subprocess.run(
        [sys.executable, "-c", script],
        input=json.dumps(commands),
        capture_output=True,
        text=True,
        cwd=cwd or REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        timeout=timeout_s * len(commands) + 60,
        check=False,
    )
    marker = proc.stdout.rfind("@@RESULT@@")
    assert marker >= 0, f"guarded run failed ({proc.returncode}): {proc.stderr[-3000:]}"
    rows = json.loads(proc.stdout[marker + len("@@RESULT@@") :])
    return [Outcome(code, out, err, None, tb) for code, out, err, tb in rows]


def snapshot(root: Path) -> dict[str, bytes | str]:
    """Every entry below ``root`` (files by content, links by target, folders by name)."""
    found: dict[str, bytes | str] = {}
    if root.is_symlink():
        return {".": f"link:{os.readlink(root)}"}
    if root.is_file():
        return {".": root.read_bytes()}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root).as_posix()
        if path.is_symlink():
            found[rel] = f"link:{os.readlink(path)}"
        elif path.is_file():
            found[rel] = path.read_bytes()
        else:
            found[rel] = "dir"
    return found


def workspace(case: Case, tmp_path: Path, dataset: Path | None) -> Workspace:
    """The case's folder, with a fresh copy of the dataset when the case uses one."""
    ds = tmp_path / "ds"
    if case.uses_dataset:
        assert dataset is not None, f"{case.id} needs the module's dataset"
        shutil.copytree(dataset, ds, symlinks=True)
    ws = Workspace(tmp_path, ds)
    for step in case.setup:
        step(ws)
    return ws


def command_line(case: Case, ws: Workspace) -> list[str]:
    return [a.format(**ws.fields()) for a in case.args]


def execute(case: Case, ws: Workspace, outcome: Outcome | None = None) -> Outcome:
    """Run ``case`` (unless a guarded run already did) and assert its expected outcome."""
    kept = {rel: snapshot(_target(ws, rel)) for rel in case.keep}
    if outcome is None:
        args = command_line(case, ws)
        with contextlib.chdir(case.cwd.format(**ws.fields()) if case.cwd else ws.tmp):
            if case.bomb:
                tracemalloc.start()
                try:
                    outcome = invoke(args)
                    peak = tracemalloc.get_traced_memory()[1]
                finally:
                    tracemalloc.stop()
                PEAKS[case.id] = peak
                print(f"\nPEAK {case.id}: {peak / 2**20:.1f} MB")
                assert peak < BOMB_PEAK_LIMIT, f"{case.id}: peak {peak / 2**20:.0f} MB"
            else:
                outcome = invoke(args)
    assert_outcome(case, outcome)
    for rel, before in kept.items():
        assert snapshot(_target(ws, rel)) == before, f"{case.id}: {rel} was changed"
    if case.check is not None:
        case.check(ws, outcome)
    return outcome


def assert_outcome(case: Case, outcome: Outcome) -> None:
    shown = f"{case.id}: exit {outcome.code}\nstdout: {outcome.stdout[-2000:]}\nstderr: "
    shown += f"{outcome.stderr[-2000:]}\n{outcome.traceback}"
    assert "Traceback" not in outcome.stdout + outcome.stderr + outcome.traceback, shown
    assert outcome.exception is None or isinstance(outcome.exception, SystemExit), shown
    if case.error is not None:
        assert outcome.code == 2, shown
        lines = outcome.stderr.strip().splitlines()
        assert len(lines) == 1, shown
        assert lines[0].startswith("coopmap: error: "), shown
        assert re.search(case.error, lines[0]), f"{shown}\nexpected /{case.error}/"
    elif case.problem is not None:
        assert outcome.code == 2, shown
        assert re.search(case.problem, outcome.stdout), f"{shown}\nexpected /{case.problem}/"
    else:
        assert case.ok is not None
        assert outcome.code == 0, shown
        assert re.search(case.ok, outcome.stdout), f"{shown}\nexpected /{case.ok}/"


def counts_table(cases: list[Case]) -> dict[tuple[str, str], int]:
    """Cases by (family, outcome), for the suite's report."""
    table: dict[tuple[str, str], int] = {}
    for case in cases:
        kind = "error" if case.error is not None else "ok" if case.ok is not None else "report"
        key = (case.family, kind)
        table[key] = table.get(key, 0) + 1
    return table


@dataclass
class Guarded:
    """Outcomes of a module's guarded cases, run together in one subprocess."""

    outcomes: dict[str, Outcome] = field(default_factory=dict)
    workspaces: dict[str, Workspace] = field(default_factory=dict)


def run_guarded(cases: list[Case], root: Path, dataset: Path | None) -> Guarded:
    """Prepare every guarded case in its own folder under ``root`` and run them all at once."""
    guarded = Guarded()
    commands = []
    for n, case in enumerate(cases):
        folder = root / f"case{n}"
        folder.mkdir(parents=True)
        ws = workspace(case, folder, dataset)
        guarded.workspaces[case.id] = ws
        commands.append(command_line(case, ws))
    for case, outcome in zip(cases, invoke_guarded(commands), strict=True):
        guarded.outcomes[case.id] = outcome
    return guarded
