"""The decode benchmark: both paths on one capture, the same scans, the command."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from estimation.app.bench.decode import run_decode_benchmark, write_benchmark_capture
from estimation.app.cli.main import app
from estimation.app.config import load_config
from estimation.app.rig import scan_limits


def test_both_paths_decode_a_written_capture_alike(tmp_path: Path) -> None:
    config = load_config()
    capture = write_benchmark_capture(tmp_path / "a.cap", scan_limits(config), telegrams=300)
    result = run_decode_benchmark(config, capture, repeats=1)
    assert (result["telegrams"], result["scans"]) == (300, 300)
    assert result["rejected"] == {}
    assert result["undecodable"] == result["checksum_failures"] == 0
    assert result["reference_us_per_telegram"] > 0
    assert result["ratio"] > 0


def test_bench_decode_command_prints_json_and_text() -> None:
    runner = CliRunner()
    result = runner.invoke(
        app, ["bench", "decode", "--json", "--telegrams", "200", "--repeats", "1"]
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert (report["benchmark"], report["telegrams"], report["scans"]) == ("decode", 200, 200)
    text = runner.invoke(app, ["bench", "decode", "--telegrams", "200", "--repeats", "1"])
    assert text.exit_code == 0, text.output
    assert "µs per telegram" in text.stdout
    assert "ratio:" in text.stdout
