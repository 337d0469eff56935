"""The LMS commands end to end: emulate a simulated sensor, record it, decode the capture."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from estimation.app.bench.scan import run_scan_benchmark
from estimation.app.cli.main import app
from estimation.app.config import Config
from estimation.app.resources import resolve_builtin
from estimation.app.rig import (
    beacon_parameters,
    driver_from_config,
    mirror_geometry,
    simulated_scan_source,
)
from sensors.lms200.emulator import Lms200Emulator
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.world import load_world

COOPMAP = Path(sys.executable).parent / "coopmap"


def test_rig_factories_follow_the_config() -> None:
    config = Config()
    geometry = mirror_geometry(config)
    assert geometry.nominal_motor_period_s == pytest.approx(0.5)
    assert geometry.axis_offset_m == config.mirror.axis_offset_m
    params = beacon_parameters(config)
    assert params["center_height_m"] == pytest.approx(1.6 - 0.45)
    driver = driver_from_config(config, "loop://", baud_rate=19200)
    assert (driver.port, driver.baud_rate, driver.angle_deg) == ("loop://", 19200, 100)


def test_scan_source_sees_the_world() -> None:
    world = load_world(resolve_builtin("worlds", "essex_lab"))
    source = simulated_scan_source(world, (6.0, 4.5, math.pi / 2), Config(), seed=1)
    ranges, flags = source(0.0, 181)
    assert ranges.shape == flags.shape == (181,)
    ranges, flags = source(1.0, 101)
    assert ranges.shape == (101,)
    # Over a whole half mirror turn every return lies inside the lab's 12 m × 9 m × 3 m box.
    scene = RaycastScene(build_mesh(world))
    assert scene.mesh.triangles.size > 0
    seen = [source(t, 101)[0] for t in np.arange(0.0, 20.0, 0.5)]
    finite = np.concatenate([r[np.isfinite(r)] for r in seen])
    assert finite.size > 1000
    assert finite.max() < math.hypot(12.0, 9.0, 3.0)


def test_emulated_world_through_the_driver(tmp_path: Path) -> None:
    world = load_world(resolve_builtin("worlds", "essex_lab"))
    source = simulated_scan_source(world, (6.0, 4.5, 0.0), Config(), seed=2)
    with Lms200Emulator(source) as emulator:
        driver = driver_from_config(
            Config(), emulator.device_path, reply_timeout_s=0.5, baud_switch_wait_s=0.02
        )
        driver.start()
        scans = list(driver.scans(limit=5))
        driver.close()
    assert len(scans) == 5
    # Half of each mirror half-turn folds the plane back onto the scanner (no returns), so
    # some scans may be empty; whatever returns lies inside the lab.
    assert all(len(s.ranges_m) == 101 and s.scan_index is not None for s in scans)
    finite = np.concatenate([s.ranges_m[np.isfinite(s.ranges_m)] for s in scans])
    assert (finite < math.hypot(12.0, 9.0, 3.0)).all()


@pytest.mark.skipif(not COOPMAP.exists(), reason="console script not installed beside python")
def test_emulate_record_decode_across_processes(tmp_path: Path) -> None:
    emulator = subprocess.Popen(
        [str(COOPMAP), "lms", "emulate", "--seconds", "20", "--pose", "6", "4.5", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert emulator.stdout is not None
        device = emulator.stdout.readline().strip()
        assert device.startswith("/dev/")
        capture = tmp_path / "run.cap"
        record = subprocess.run(
            [str(COOPMAP), "lms", "record", "--port", device, "--out", str(capture), "--scans", "8"],
            capture_output=True, text=True, timeout=30, check=False,
        )  # fmt: skip
        assert record.returncode == 0, record.stderr
        assert f"wrote {capture}" in record.stdout
        decoded = subprocess.run(
            [str(COOPMAP), "lms", "decode", str(capture), "--json"],
            capture_output=True, text=True, timeout=30, check=True,
        )  # fmt: skip
        lines = [json.loads(line) for line in decoded.stdout.splitlines()]
        summary = lines[-1]
        assert summary["kind"] == "summary"
        assert summary["scans"] >= 8
        assert summary["checksum_failures"] == 0
        scans = [line for line in lines if line["kind"] == "scan"]
        assert all(len(s["ranges_m"]) == 101 for s in scans)
        assert all(s["scan_index"] is not None for s in scans)  # real-time indices were enabled
    finally:
        emulator.terminate()
        emulator.wait(timeout=10)


def test_emulate_rejects_a_pose_outside_the_world() -> None:
    result = CliRunner().invoke(
        app, ["lms", "emulate", "--pose", "50", "50", "0", "--seconds", "0.1"]
    )
    assert result.exit_code == 2
    assert "pose (50, 50) lies outside every room of essex_lab" in result.stderr


def test_record_errors_are_one_line(tmp_path: Path) -> None:
    existing = tmp_path / "old.cap"
    existing.write_bytes(b"keep me")
    result = CliRunner().invoke(app, ["lms", "record", "--port", "loop://", "--out", str(existing)])
    assert result.exit_code == 2
    assert "already exists" in result.stderr
    assert existing.read_bytes() == b"keep me"
    result = CliRunner().invoke(
        app, ["lms", "record", "--port", "/dev/no-such-port", "--out", str(tmp_path / "new.cap")]
    )
    assert result.exit_code == 2
    assert "cannot open /dev/no-such-port" in result.stderr
    assert not (tmp_path / "new.cap").exists()


def test_scan_benchmark_reports_its_figures() -> None:
    result = run_scan_benchmark(Config(), repeats=2)
    assert result["benchmark"] == "scan"
    assert 240 <= result["telegrams"] <= 260
    assert result["points"] > 5000
    assert result["ratio"] == pytest.approx(result["sweep_seconds"] * 1e3 / result["milliseconds"])
