"""Running ``coopmap`` in-process in tests, and the one-line error every known failure gives."""

from __future__ import annotations

import re
from pathlib import Path

from typer.testing import CliRunner

from estimation.app.cli.main import app


def run(*args: str | Path) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``coopmap ARGS``."""
    result = CliRunner().invoke(app, [str(a) for a in args])
    return result.exit_code, result.stdout, result.stderr


def assert_one_line_error(code: int, stdout: str, stderr: str, pattern: str) -> None:
    """Exit code 2, no traceback, and one ``coopmap: error:`` line on stderr matching ``pattern``."""
    assert code == 2
    assert "Traceback" not in stdout + stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("coopmap: error: ")
    assert re.search(pattern, lines[0]), lines[0]
