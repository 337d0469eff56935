"""``coopmap bench live``: its report and its bad input (the live runs themselves are
tests/estimation/app/live/test_supervisor.py's)."""

from __future__ import annotations

from pathlib import Path

import yaml

from estimation.app.bench.live import format_live_report, peer_mission
from estimation.app.resources import resolve_builtin
from tests.estimation.app.cli.clirun import assert_one_line_error, run

ROBOT = {"chunks": 74, "bytes": 1_500_000, "bytes_per_s": 142_000.0, "queried_from_disk": 2,
         "scan_to_map_s": {"p50": 0.282, "p99": 0.832, "chunks": 13},
         "command_latency_s": {"p50": 0.06, "p99": 0.797}}  # fmt: skip
RESULT = {"mission": "essex_lab", "robots": ["a", "b"], "faults": None, "live_wall_s": [18.6, 20.0],
          "in_process_wall_s": 12.0, "mission_s": 459.0, "dwells": 13,
          "work_per_dwell_s": {"median": 0.26, "p99": 0.71},
          "network": {"robots": {"a": ROBOT}}}  # fmt: skip


def test_the_report_prints_the_ratio_and_the_latencies() -> None:
    text = format_live_report(RESULT)
    assert "live 18.6 s (best of 2; worst 20.0 s), in one process 12.0 s: 1.55x" in text
    assert "scan -> map p50 282 ms, p99 832 ms; 142 kB/s (1.5 MB in 74 chunks)" in text
    assert "2 chunks queried from its disk" in text


def test_the_peer_flies_the_mission_on_its_map(tmp_path: Path) -> None:
    path = peer_mission(resolve_builtin("missions", Path("essex_lab")), tmp_path)
    document = yaml.safe_load(path.read_text())
    assert document["auto"]["planner"] == "map"
    assert document["world"] == "essex_lab"


def test_bad_faults_are_one_line() -> None:
    assert_one_line_error(*run("bench", "live", "--faults", "drop=2"), r"drop must be in")
