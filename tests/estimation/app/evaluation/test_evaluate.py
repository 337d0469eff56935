"""report.json as evaluate reads it: anything but a coopmap report is a one-line error."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from estimation.app.cli.main import app
from estimation.app.evaluation.evaluate import read_report
from estimation.errors import EstimationError

GOOD = {
    "robots": {"a": {"poses": 3}},
    "observations": 2,
    "gate_rejections": [],
    "outlier_factors": [],
    "timings_s": {"decode": 0.1, "total": 0.1},
    "missing_sweeps": [],
    "unseen_pairs": [],
    "dropped_poses": [],
    "global_localization": {"searches": [{"station": "a3", "against": "b2", "pose": [0, 0, 0]}]},
}


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (json.dumps(GOOD)[:40].encode(), r"not a coopmap report \(not JSON"),
        (b"{}", r"robots: required key is missing"),
        (b"[1, 2]", r"not a coopmap report \(a list\)"),
        (b"\xff\xfe\x00garbage", "not UTF-8 text"),
        (b"[" * 100_000 + b"]" * 100_000, r"not a coopmap report \(not JSON: nested too deeply\)"),
        (json.dumps({**GOOD, "robots": {"../../x": {}}}).encode(), r"robots\.\.\./\.\./x"),
        (json.dumps({**GOOD, "observations": "many"}).encode(), r"observations"),
        (
            json.dumps({**GOOD, "global_localization": {"searches": [{"station": "a3"}]}}).encode(),
            r"global_localization\.searches\[0\]\.against: required key is missing",
        ),
    ],
)
def test_foreign_reports_are_one_line_errors(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "report.json"
    path.write_bytes(content)
    with pytest.raises(EstimationError, match=message):
        read_report(path)


def test_a_coopmap_report_reads_back(tmp_path: Path) -> None:
    path = tmp_path / "report.json"
    path.write_text(json.dumps(GOOD))
    assert read_report(path)["robots"] == {"a": {"poses": 3}}


def test_evaluate_on_a_foreign_report_exits_with_one_line(tmp_path: Path) -> None:
    result_dir = tmp_path / "result"
    result_dir.mkdir()
    (result_dir / "report.json").write_text("{}")
    result = CliRunner().invoke(app, ["evaluate", str(tmp_path), "--result", str(result_dir)])
    assert result.exit_code == 2
    assert result.stderr.count("\n") == 1
    assert "not a coopmap report" in result.stderr


def test_evaluate_does_not_write_through_a_linked_result(tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "report.json").write_text(json.dumps(GOOD))
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "result").symlink_to(elsewhere)
    result = CliRunner().invoke(app, ["evaluate", str(tmp_path / "ds")])
    assert result.exit_code == 2
    assert "is a symbolic link" in result.stderr
    assert sorted(p.name for p in elsewhere.iterdir()) == ["report.json"]
