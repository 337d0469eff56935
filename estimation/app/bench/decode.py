"""``coopmap bench decode``: decoding a mission's LMS capture, per telegram and vectorised.

A capture the size of office_loop's (38,000 telegrams of 101 values with real-time indices at
38 400 Bd, one record per telegram as the simulator writes them; a mirror that folds a third of
the beams away) is written once, or an existing capture is read. The per-telegram reference
(:class:`~sensors.lms200.reference.ReferenceDecoder`: records one by one, a ``Telegram`` per
frame, numpy per telegram, the rules in Python) and the vectorised
:class:`~sensors.lms200.decoder.ScanDecoder` decode it in the same process, each with the
plausibility rules of the configured scanner; both must yield the same scans and counts.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from estimation.app.config import Config
from estimation.app.rig import scan_limits
from sensors.lms200.capture import CaptureReader, CaptureWriter
from sensors.lms200.decoder import ScanDecoder
from sensors.lms200.protocol.plausibility import ScanLimits
from sensors.lms200.protocol.scan import Scan, encode_scan
from sensors.lms200.protocol.telegram import TURN_S
from sensors.lms200.reference import ReferenceDecoder

__all__ = ["format_decode_report", "run_decode_benchmark", "write_benchmark_capture"]

#: office_loop's capture of one robot: 37,961 telegrams.
TELEGRAMS = 38_000


def write_benchmark_capture(
    path: Path, limits: ScanLimits, telegrams: int = TELEGRAMS, seed: int = 0
) -> Path:
    """Continuous output of the configured variant, one record per telegram."""
    rng = np.random.default_rng(seed)
    turns = limits.turns_per_telegram
    with CaptureWriter(path, {"baud_rate": limits.baud_rate}) as writer:
        for k in range(telegrams):
            ranges = rng.uniform(0.3, 7.5, limits.count)
            ranges[rng.random(limits.count) < 0.35] = np.nan
            turn = 100 + turns * k
            data = encode_scan(ranges, unit_mm=limits.unit_mm, scan_index=turn & 0xFF,
                               telegram_index=k & 0xFF)  # fmt: skip
            writer.write((turn + 1) * TURN_S + len(data) * 10 / limits.baud_rate + 0.002, data)
    return path


def _counts(
    telegrams: int, failures: int, undecodable: int, rejected: dict[str, int]
) -> dict[str, Any]:
    return {"telegrams": telegrams, "checksum_failures": failures, "undecodable": undecodable,
            "rejected": dict(rejected)}  # fmt: skip


def _reference(path: Path, mode: int, limits: ScanLimits) -> tuple[list[Scan], dict[str, Any]]:
    decoder = ReferenceDecoder(mode, limits)
    scans = decoder.decode(CaptureReader(path))
    stats = decoder.parser.stats
    assert decoder.check is not None
    return scans, _counts(stats.telegrams, stats.checksum_failures, decoder.undecodable,
                          decoder.check.rejected)  # fmt: skip


def _vectorised(path: Path, mode: int, limits: ScanLimits) -> tuple[list[Scan], dict[str, Any]]:
    decoder = ScanDecoder(mode, limits)
    scans = decoder.feed_stream(CaptureReader(path).stream()) + decoder.close()
    stats = decoder.stats
    assert decoder.check is not None
    return scans, _counts(stats.telegrams, stats.checksum_failures, stats.undecodable,
                          decoder.check.rejected)  # fmt: skip


def run_decode_benchmark(
    config: Config, capture: Path | None = None, telegrams: int = TELEGRAMS, repeats: int = 3
) -> dict[str, Any]:
    """Best of ``repeats`` for each path on one capture (written to a temporary folder if none
    is given); raises AssertionError if the two paths disagree."""
    limits = scan_limits(config)
    mode = config.scanner.measuring_mode
    with tempfile.TemporaryDirectory() as folder:
        if capture is None:
            capture = write_benchmark_capture(Path(folder) / "bench.cap", limits, telegrams)
        header = CaptureReader(capture).header or {}
        if header.get("baud_rate") in (9600, 19200, 38400, 500000):
            limits = ScanLimits(limits.count, limits.unit_mm, int(header["baud_rate"]))
        _vectorised(capture, mode, limits)  # warm-up: compiled kernels load from the numba cache
        seconds: dict[str, list[float]] = {"reference": [], "vectorised": []}
        results = {}
        for _ in range(repeats):
            for name, run in (("reference", _reference), ("vectorised", _vectorised)):
                begin = time.perf_counter()
                results[name] = run(capture, mode, limits)
                seconds[name].append(time.perf_counter() - begin)
        size = capture.stat().st_size
    (ref_scans, ref_counts), (new_scans, new_counts) = results["reference"], results["vectorised"]
    assert ref_counts == new_counts, (ref_counts, new_counts)
    assert len(ref_scans) == len(new_scans)
    assert all(np.array_equal(a.raw, b.raw) and a.stamp_s == b.stamp_s
               for a, b in zip(ref_scans, new_scans, strict=True))  # fmt: skip
    count = ref_counts["telegrams"]
    best = {name: min(times) for name, times in seconds.items()}
    return {
        "benchmark": "decode",
        "telegrams": count,
        "scans": len(new_scans),
        "bytes": size,
        "reference_us_per_telegram": best["reference"] / count * 1e6,
        "vectorised_us_per_telegram": best["vectorised"] / count * 1e6,
        "reference_median_s": statistics.median(seconds["reference"]),
        "vectorised_median_s": statistics.median(seconds["vectorised"]),
        "ratio": best["reference"] / best["vectorised"],
        "repeats": repeats,
        **{k: v for k, v in new_counts.items() if k != "telegrams"},
    }


def format_decode_report(result: dict[str, Any]) -> str:
    return (
        f"bench decode: {result['telegrams']:,} telegrams ({result['bytes']:,} bytes, "
        f"{result['scans']:,} plausible scans), best of {result['repeats']}\n"
        f"  per-telegram reference: {result['reference_us_per_telegram']:.2f} µs per telegram\n"
        f"  vectorised ScanDecoder: {result['vectorised_us_per_telegram']:.2f} µs per telegram\n"
        f"  ratio: {result['ratio']:.1f}× (same scans and counts: checked)"
    )
