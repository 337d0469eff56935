"""``coopmap bench scan``: decoding and 3D conversion of one full 3D scan, against real time.

A simulated 20 s half mirror turn of essex_lab at 38 400 Bd (≈250 telegrams × 101 values) is
turned into bytes once; then the parser, the B0 decoding, the scan timing, the mirror
estimation and the sweep assembly run on those bytes repeatedly. The peer is the scanner
itself: the ratio is the 20 s the sweep takes to record over the processing time.
"""

from __future__ import annotations

import math
import statistics
import time
from typing import Any

import numpy as np

from estimation.app.config import Config
from estimation.app.resources import resolve_builtin
from estimation.app.rig import mirror_geometry, simulated_scanner
from sensors.geometry.frames import scanner_pose_matrix
from sensors.lms200.protocol.scan import decode_scan
from sensors.lms200.protocol.stream import StreamParser, Telegram
from sensors.scan3d.mirror import assemble_sweeps, estimate_mirror, scan_times
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.sensing import scan_stream, telegram_times
from sensors.sim.world import load_world

__all__ = ["run_scan_benchmark"]


def _process(chunks: list[tuple[float, bytes]], config: Config) -> tuple[int, int]:
    parser = StreamParser()
    scans = [
        decode_scan(event, config.scanner.measuring_mode)
        for stamp, chunk in chunks
        for event in parser.feed(chunk, stamp)
        if isinstance(event, Telegram) and event.code == 0xB0
    ]
    times = scan_times(scans)
    sweeps = assemble_sweeps(scans, times, estimate_mirror(scans, times, mirror_geometry(config)))
    return len(scans), sum(len(s) for s in sweeps)


def run_scan_benchmark(config: Config, repeats: int = 20, seed: int = 0) -> dict[str, Any]:
    world = load_world(resolve_builtin("worlds", "essex_lab"))
    scene = RaycastScene(build_mesh(world))
    rng = np.random.default_rng(seed)
    scanner = simulated_scanner(config, rng)
    sweep_s = scanner.motor_period_s * scanner.geometry.half_turn_motor_turns
    # One sweep, aligned so that the whole valid half (centred on edge-on) falls inside it.
    start = scanner.edge_on_time_s - sweep_s / 2
    times = telegram_times(start, sweep_s, config.serial.baud_rate, 101, 1.0)
    simulated = scanner.scan(
        scene,
        scanner_pose_matrix(
            6.0, 4.5, math.pi / 2, config.robot.scanner_x_m, config.robot.scanner_height_m
        ),
        times,
        rng,
    )
    chunks = scan_stream(simulated, baud_rate=config.serial.baud_rate)
    _process(chunks, config)  # warm-up: compiled kernels load from the numba cache
    seconds = []
    for _ in range(repeats):
        begin = time.perf_counter()
        telegrams, points = _process(chunks, config)
        seconds.append(time.perf_counter() - begin)
    median = statistics.median(seconds)
    return {
        "benchmark": "scan",
        "ratio": sweep_s / median,
        "milliseconds": median * 1e3,
        "milliseconds_max": max(seconds) * 1e3,
        "sweep_seconds": sweep_s,
        "telegrams": telegrams,
        "bytes": sum(len(c) for _, c in chunks),
        "points": points,
        "repeats": repeats,
    }
