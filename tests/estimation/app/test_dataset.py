"""Decoding a robot's capture: implausible scans are dropped and counted by reason."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from estimation.app.config import ConfigError
from estimation.app.dataset import (
    DWELL_SETTLE_S,
    LmsDecoder,
    RobotStream,
    decode_dwells,
    decode_robot,
    load_dataset,
    sweep_in,
    with_dwell_sweeps,
)
from estimation.app.rig import beacon_parameters
from sensors.errors import SensorError
from sensors.lms200.capture import CaptureReader, CaptureWriter
from sensors.lms200.protocol.plausibility import ScanLimits
from sensors.lms200.protocol.scan import encode_scan, scan_interval_s
from sensors.lms200.protocol.telegram import TURN_S
from sensors.scan3d.beacon import detect_beacons

LIMITS = ScanLimits.for_variant(100, 1.0, unit_mm=True, baud_rate=38400)


def write_capture(path: Path, baud_rate: int, corrupt: dict[int, dict[str, object]]) -> Path:
    """200 telegrams of continuous output at ``baud_rate``; ``corrupt`` replaces the encoder's
    arguments of some (each still has a valid checksum)."""
    turns = round(scan_interval_s(baud_rate, 101, 1.0, True) / TURN_S)
    with CaptureWriter(path, {"baud_rate": baud_rate}) as writer:
        for k in range(200):
            turn = 500 + turns * k
            options: dict[str, object] = {"scan_index": turn & 0xFF, "telegram_index": k & 0xFF}
            options.update(corrupt.get(k, {}))
            data = encode_scan(np.full(101, 3.0), **options)  # type: ignore[arg-type]
            writer.write((turn + 1) * TURN_S + len(data) * 10 / baud_rate + 0.002, data)
    return path


def test_implausible_scans_are_dropped_and_counted(tmp_path: Path) -> None:
    corrupt = {50: {"scan_index": 3}, 120: {"unit_mm": False}, 121: {"status": 0x17}}
    capture = write_capture(tmp_path / "a.cap", 38400, corrupt)
    stream = decode_robot(capture, 1, LIMITS)
    assert len(stream.scans) == 197
    assert stream.implausible == {"sequence": 1, "unit": 1, "status": 1}
    assert stream.implausible_scans == 3
    assert stream.telegrams == 200
    steps = np.diff(stream.times_s) / TURN_S
    assert set(np.round(steps).astype(int)) == {6, 12, 18}  # the gaps left by the three
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    unchecked = decode_robot(capture, 1)
    assert (len(unchecked.scans), unchecked.implausible) == (200, {})
    # Unchecked, the one bad scan index shifts every later scan by 256 turns (3.4 s).
    span = unchecked.times_s[-1] - unchecked.times_s[0]
    assert span == pytest.approx(stream.times_s[-1] - stream.times_s[0] + 256 * TURN_S, abs=1e-6)


def test_the_capture_header_sets_the_telegram_interval(tmp_path: Path) -> None:
    """Recorded at 500 kBd a telegram leaves every turn; the configured 38 400 Bd is overruled."""
    capture = write_capture(tmp_path / "fast.cap", 500000, {})
    stream = decode_robot(capture, 1, LIMITS)
    assert (len(stream.scans), stream.implausible_scans) == (200, 0)


def test_a_capture_of_another_variant_is_a_clear_error(tmp_path: Path) -> None:
    capture = write_capture(tmp_path / "a.cap", 38400, {})
    other = ScanLimits.for_variant(180, 1.0, unit_mm=True, baud_rate=38400)
    with pytest.raises(SensorError, match=r"all 200 scans are implausible .*\(200 count\)"):
        decode_robot(capture, 1, other)


def write_streamed_capture(path: Path, rng: np.random.Generator) -> Path:
    """300 telegrams as a serial port delivers them: in records of random size (a telegram
    spans several; some records run a few bytes into the next telegram), each stamped when its
    last byte came in, with line noise, a telegram whose checksum is broken, one with an
    impossible scan index (implausible) and a gap of dropped telegrams."""
    baud = 38400
    byte_s = 10 / baud
    turns = round(scan_interval_s(baud, 101, 1.0, True) / TURN_S)
    stream = bytearray()
    arrival: list[float] = []  # when each byte of the stream was received (s)
    cuts: set[int] = set()
    for k in range(300):
        if 100 <= k < 104:
            continue  # dropped: a gap of four telegrams
        turn = 700 + turns * k
        index = 3 if k == 200 else turn & 0xFF
        data = bytearray(encode_scan(rng.uniform(0.5, 7.0, 101), scan_index=index,
                                     telegram_index=k & 0xFF))  # fmt: skip
        if k == 150:
            data[20] ^= 0x40  # the checksum no longer matches
        if k in (50, 250):
            data[:0] = bytes([0x02, 0x80, 0xFF, 0x7F, 0x11, 0x02])  # noise with false starts
        done_s = (turn + 1) * TURN_S + len(data) * byte_s + 0.002
        arrival += [done_s - (len(data) - 1 - b) * byte_s for b in range(len(data))]
        cuts.update((len(stream) + rng.integers(1, len(data), int(rng.integers(0, 4)))).tolist())
        stream += data
        # A read ends at the telegram's end, or runs on into the next one for a few bytes
        # (a millisecond or two: the lateness of the stamps stays within what the sequence
        # check allows).
        cuts.add(len(stream) + (int(rng.integers(1, 8)) if rng.random() < 0.3 else 0))
    with CaptureWriter(path, {"baud_rate": baud}) as writer:
        start = 0
        for end in [*sorted(c for c in cuts if c < len(stream)), len(stream)]:
            stamp = arrival[end - 1] + float(rng.uniform(0.0, 0.001))
            writer.write(stamp, bytes(stream[start:end]))
            start = end
    return path


def assert_same_stream(got: RobotStream, expected: RobotStream) -> None:
    assert len(got.scans) == len(expected.scans)
    np.testing.assert_array_equal(got.times_s, expected.times_s)
    assert [s.scan_index for s in got.scans] == [s.scan_index for s in expected.scans]
    assert [s.stamp_s for s in got.scans] == [s.stamp_s for s in expected.scans]
    for a, b in zip(got.scans, expected.scans, strict=True):
        np.testing.assert_array_equal(a.raw, b.raw)
    counters = ("telegrams", "undecodable", "checksum_failures", "bytes_skipped",
                "truncated_bytes", "corrupt_bytes", "implausible")  # fmt: skip
    assert {c: getattr(got, c) for c in counters} == {c: getattr(expected, c) for c in counters}


def test_lms_decoder_fed_chunk_by_chunk_gives_what_decode_robot_gives(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    capture = write_streamed_capture(tmp_path / "a.cap", rng)
    expected = decode_robot(capture, 1, LIMITS)
    # The capture exercises every counter the stream keeps.
    assert expected.telegrams == 295
    assert expected.checksum_failures == 1
    assert expected.implausible == {"sequence": 1}
    assert len(expected.scans) == 294
    assert expected.bytes_skipped > 0
    assert np.diff(expected.times_s).min() > 0
    reader = CaptureReader(capture)
    chunks = list(reader.chunks())
    assert len(chunks) > 400  # telegrams (732 bytes) span several records
    decoder = LmsDecoder(1, LIMITS, reader.header)
    completed = [decoder.feed(stamp, chunk) for stamp, chunk in chunks]
    assert sum(completed) == len(expected.scans)
    assert max(completed) == 1  # no record holds two whole telegrams
    decoder.close()
    assert_same_stream(decoder.stream(reader.truncated_bytes, reader.corrupt_bytes), expected)


def test_lms_decoder_does_not_depend_on_how_the_bytes_are_split(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    capture = write_streamed_capture(tmp_path / "a.cap", rng)
    expected = decode_robot(capture, 1, LIMITS)
    reader = CaptureReader(capture)
    chunks = list(reader.chunks())
    for trial in range(3):
        decoder = LmsDecoder(1, LIMITS, reader.header)
        midway: RobotStream | None = None
        for n, (stamp, chunk) in enumerate(chunks):
            # Each record in pieces (single bytes and empty pieces included), same stamp.
            cuts = np.sort(rng.integers(0, len(chunk) + 1, int(rng.integers(0, 6))))
            for a, b in itertools.pairwise([0, *cuts.tolist(), len(chunk)]):
                decoder.feed(stamp, chunk[a:b])
            if n == len(chunks) // 2 and trial == 0:
                midway = decoder.stream()
        decoder.close()
        assert_same_stream(decoder.stream(reader.truncated_bytes, reader.corrupt_bytes), expected)
        if midway is not None:
            # The times so far are the whole stream's, but for the anchor: the earliest
            # arrival so far, which later scans can only lower (by a few ms of latency).
            count = len(midway.times_s)
            assert 0 < count < len(expected.scans)
            shift = midway.times_s - expected.times_s[:count]
            assert shift.min() >= 0.0
            assert shift.max() < 0.005
            np.testing.assert_allclose(shift, shift[0], atol=1e-9)


def minimal_dataset(folder: Path) -> Path:
    """mission.yaml with two robots and an empty events.jsonl: what load_dataset reads."""
    folder.mkdir()
    (folder / "mission.yaml").write_text(
        "robots:\n  - {name: a, start: [0, 0, 0]}\n  - {name: b, start: [2, 0, 180]}\n",
        encoding="utf-8",
    )
    (folder / "events.jsonl").write_text("", encoding="utf-8")
    return folder


@pytest.mark.parametrize(
    ("note", "expected"),
    [
        (None, None),
        ('{"failure": "Indeterminate linear system", "dwells": 7}', "Indeterminate linear system"),
    ],
)
def test_a_partial_dataset_says_why_its_mission_failed(
    tmp_path: Path, note: str | None, expected: str | None
) -> None:
    folder = minimal_dataset(tmp_path / "dataset")
    if note is not None:
        (folder / "partial.json").write_text(note, encoding="utf-8")
    assert load_dataset(folder).partial == expected


@pytest.mark.parametrize(
    ("note", "message"),
    [
        ('{"failure": ', r"partial\.json: not JSON \(Expecting value, line 1\)"),
        ('{"failure": 3}', r"partial\.json: no failure \(a string\) recorded"),
        ("[1, 2]", r"partial\.json: no failure \(a string\) recorded"),
        (b"\xff\xfe", r"partial\.json"),
    ],
)
def test_a_corrupt_partial_note_is_a_one_line_error(
    tmp_path: Path, note: str | bytes, message: str
) -> None:
    folder = minimal_dataset(tmp_path / "dataset")
    path = folder / "partial.json"
    if isinstance(note, bytes):
        path.write_bytes(note)
    else:
        path.write_text(note, encoding="utf-8")
    with pytest.raises(ConfigError, match=message):
        load_dataset(folder)


def test_a_stream_holding_its_dwells_sweeps_gives_the_sweeps_its_scans_gave(
    essex_simulated: Path,
) -> None:
    """``batch`` keeps one robot's scans at a time: the sweeps made from them while they are at
    hand are the sweeps the event stream would have made, and the scans are let go."""
    dataset = load_dataset(essex_simulated)
    capture = essex_simulated / "robots" / "a" / "lms.cap"
    stream = decode_robot(capture, dataset.config.scanner.measuring_mode)
    held = with_dwell_sweeps(stream, dataset.events, dataset.config)
    assert (held.scans, len(held.times_s)) == ([], 0)
    assert (held.telegrams, held.undecodable) == (stream.telegrams, stream.undecodable)
    dwells = [(n, e) for n, e in enumerate(dataset.events) if e["event"] == "dwell"]
    assert sorted(held.dwell_sweeps) == [n for n, _ in dwells]
    assert len(dwells) > 5
    for number, entry in dwells:
        made, why = held.sweep_of(number, entry, dataset.config)
        expected, expected_why = sweep_in(
            stream, entry["t_s"] + DWELL_SETTLE_S, entry["end_s"], dataset.config
        )
        assert why == expected_why
        assert (made is None) == (expected is None)
        if made is not None and expected is not None:
            # Kept in float32: the same points rounded.
            assert made.points_scanner.dtype == np.float32
            np.testing.assert_array_equal(made.points_scanner,
                                          expected.points_scanner.astype(np.float32))  # fmt: skip
            np.testing.assert_array_equal(made.reflector, expected.reflector)
            assert len(made) == len(expected)
            assert made.range_m.size == made.stamp_s.size == made.flags.size == 0  # trimmed
            assert (made.start_s, made.end_s, made.scans) == (
                expected.start_s, expected.end_s, expected.scans
            )  # fmt: skip
            # The beacons found as the sweep was made, as the event stream would find them.
            found, _ = detect_beacons(expected.points_scanner, expected.reflector,
                                      **beacon_parameters(dataset.config))  # fmt: skip
            held_found = held.dwell_beacons[number]
            assert [d.center_scanner.tolist() for d in held_found] == [
                d.center_scanner.tolist() for d in found
            ]
        else:
            assert number not in held.dwell_beacons
    assert any(held.dwell_beacons.values())  # essex_lab's robots see each other
    # A dwell it does not hold is made from the scans it holds (none now): no sweep, and why.
    number, entry = dwells[0]
    empty = with_dwell_sweeps(stream, [], dataset.config)
    assert empty.sweep_of(number, entry, dataset.config) == (None, "only 0 scans in the dwell")


def test_decoding_a_robots_dwells_is_decoding_then_keeping_the_sweeps(
    essex_simulated: Path,
) -> None:
    dataset = load_dataset(essex_simulated)
    capture = essex_simulated / "robots" / "b" / "lms.cap"
    mode = dataset.config.scanner.measuring_mode
    stream, decode_s, sweeps_s = decode_dwells(capture, mode, None, dataset.events, dataset.config)
    held = with_dwell_sweeps(decode_robot(capture, mode), dataset.events, dataset.config)
    assert decode_s > 0.0
    assert sweeps_s > 0.0
    assert stream.telegrams == held.telegrams > 0
    assert sorted(stream.dwell_sweeps) == sorted(held.dwell_sweeps)
    for number, (sweep, why) in held.dwell_sweeps.items():
        other, other_why = stream.dwell_sweeps[number]
        assert other_why == why
        if sweep is not None:
            assert other is not None
            np.testing.assert_array_equal(other.points_scanner, sweep.points_scanner)
