"""The vectorised decoder gives what the per-telegram reference gives, scan for scan and count
for count, on clean and on corrupted captures, whole or fed a chunk at a time."""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sensors.lms200.capture import MAGIC, CaptureReader, CaptureWriter
from sensors.lms200.decoder import ScanDecoder
from sensors.lms200.protocol.plausibility import ScanLimits
from sensors.lms200.protocol.replies import encode_mode_reply
from sensors.lms200.protocol.scan import Scan, encode_scan, scan_interval_s
from sensors.lms200.protocol.telegram import ACK, TURN_S, reply_frame
from sensors.lms200.reference import ReferenceDecoder

LIMITS = ScanLimits.for_variant(100, 1.0, unit_mm=True, baud_rate=38400)
TURNS = round(scan_interval_s(38400, 101, 1.0, True) / TURN_S)
#: Telegrams a sensor can send but the configured one cannot (each passes the checksum), and
#: malformed measured-value telegrams.
ODD = (
    "range", "undocumented", "flags", "status", "scan_index", "telegram_index", "unit",
    "count", "partial", "count_bits", "short", "size", "reserved_unit", "other_reply", "ack",
    "garbage",
)  # fmt: skip


def words_frame(words: np.ndarray, count_word: int, tail: bytes = b"", status: int = 0x10) -> bytes:
    payload = struct.pack("<H", count_word) + np.asarray(words, "<u2").tobytes() + tail
    return reply_frame(0xB0, payload, status)


def telegram(kind: str, k: int, rng: np.random.Generator) -> bytes:
    """Telegram ``k`` of continuous output (real-time indices on), spoilt as ``kind`` says."""
    turn = 1000 + TURNS * k
    index = {"scan_index": turn & 0xFF, "telegram_index": k & 0xFF}
    ranges = rng.uniform(0.2, 7.5, 101)
    ranges[rng.random(101) < 0.1] = np.nan
    tail = bytes((turn & 0xFF, k & 0xFF))
    words = np.round(rng.uniform(200, 7000, 101)).astype(np.int64)
    if kind == "range":
        ranges[int(rng.integers(101))] = 8.15  # beyond mode 1's 8 m (+1 %), below its mask
    elif kind == "scan_index":
        index["scan_index"] = int(rng.integers(256))
    elif kind == "telegram_index":
        index["telegram_index"] = int(rng.integers(256))
    elif kind == "undocumented":
        words[int(rng.integers(101))] = 0x1FFF - 3
        return words_frame(words, 101 | 0x4000, tail)
    elif kind == "flags":
        words[int(rng.integers(101))] |= 0x8000  # no mode sets bit 15 but mode 15 (none)
        return words_frame(words, 101 | 0x4000, tail)
    elif kind == "count":
        return words_frame(words[:100], 100 | 0x4000, tail)  # malformed: no such variant
    elif kind == "partial":
        return words_frame(words[:37], 37 | 0x4000 | 0x2000 | 0x0800, tail)
    elif kind == "count_bits":
        return words_frame(words, 101 | 0x4000 | 0x0400, tail)
    elif kind == "short":
        return reply_frame(0xB0, b"\x01")
    elif kind == "size":
        return words_frame(words, 101 | 0x4000, tail + b"\x00")
    elif kind == "reserved_unit":
        return words_frame(words, 101 | 0x8000, tail)
    elif kind == "other_reply":
        return encode_mode_reply(0)
    elif kind == "ack":
        return bytes((ACK,))
    elif kind == "garbage":
        return rng.integers(0, 256, int(rng.integers(1, 40))).astype(np.uint8).tobytes()
    options: dict[str, object] = dict(index)
    if kind == "status":
        options["status"] = 0x17
    elif kind == "unit":
        options["unit_mm"] = False
        ranges = np.clip(ranges, 0.2, 7.5)
    flags = rng.integers(0, 8, 101) * (rng.random(101) < 0.05)
    return encode_scan(ranges, flags=flags, **options)  # type: ignore[arg-type]


def write_capture(path: Path, kinds: list[str], rng: np.random.Generator) -> Path:
    """The telegrams as a port delivers them: records of random size, stamped on arrival."""
    stream = bytearray()
    stamps: list[float] = []  # the arrival of each byte
    ends: list[int] = []
    for k, kind in enumerate(kinds):
        data = telegram(kind, k, rng)
        done_s = (1000 + TURNS * k + 1) * TURN_S + len(data) * 10 / 38400 + 0.002
        stamps += [done_s - (len(data) - 1 - b) * 10 / 38400 for b in range(len(data))]
        stream += data
        ends.append(len(stream))
    # A read ends where a telegram ends, or a few bytes on; some end inside telegrams.
    inside = rng.integers(1, max(2, len(stream)), len(kinds) // 2 + 1)
    late = np.array(ends) + rng.integers(0, 8, len(ends)) * (rng.random(len(ends)) < 0.3)
    cuts = np.unique(np.concatenate([inside, late]))
    cuts = cuts[cuts < len(stream)]
    with CaptureWriter(path, {"baud_rate": 38400}) as writer:
        for a, b in zip([0, *cuts.tolist()], [*cuts.tolist(), len(stream)], strict=True):
            if b > a:
                writer.write(stamps[b - 1] + float(rng.uniform(0, 0.001)), bytes(stream[a:b]))
    return path


def spoil(path: Path, rng: np.random.Generator, flips: int, inserts: int, cut: int) -> None:
    """Bit flips, garbage stretches and a truncation anywhere after the capture's header."""
    content = bytearray(path.read_bytes())
    start = content.index(b"\n", len(MAGIC)) + 1
    for _ in range(flips):
        content[int(rng.integers(start, len(content)))] ^= 1 << int(rng.integers(8))
    for _ in range(inserts):
        at = int(rng.integers(start, len(content)))
        content[at:at] = rng.integers(0, 256, int(rng.integers(1, 60))).astype(np.uint8).tobytes()
    del content[max(start, len(content) - cut) :]
    path.write_bytes(bytes(content))


def assert_same_scans(got: list[Scan], expected: list[Scan]) -> None:
    assert len(got) == len(expected)
    for a, b in zip(got, expected, strict=True):
        for f in dataclasses.fields(Scan):
            x, y = getattr(a, f.name), getattr(b, f.name)
            if isinstance(y, np.ndarray):
                assert x.dtype == y.dtype, f.name
                np.testing.assert_array_equal(x, y, err_msg=f.name)
            else:
                assert type(x) is type(y), (f.name, x, y)
                assert x == y, (f.name, x, y)


def counters(decoder: ScanDecoder | ReferenceDecoder, reader: CaptureReader) -> dict[str, object]:
    if isinstance(decoder, ScanDecoder):
        stats = decoder.stats
        telegrams, failures, skipped = stats.telegrams, stats.checksum_failures, stats.bytes_skipped
        decoded, undecodable = stats.decoded, stats.undecodable
    else:
        parser = decoder.parser.stats
        telegrams, failures, skipped = (
            parser.telegrams,
            parser.checksum_failures,
            parser.bytes_skipped,
        )
        decoded, undecodable = decoder.decoded, decoder.undecodable
    rejected = list(decoder.check.rejected.items()) if decoder.check is not None else []
    return {
        "telegrams": telegrams, "checksum_failures": failures, "bytes_skipped": skipped,
        "decoded": decoded, "undecodable": undecodable, "rejected": rejected,
        "accepted": decoder.check.accepted if decoder.check is not None else None,
        "truncated": reader.truncated_bytes, "corrupt": reader.corrupt_bytes,
        "resyncs": reader.resyncs,
    }  # fmt: skip


def assert_all_agree(path: Path, measuring_mode: int, limits: ScanLimits | None) -> list[Scan]:
    """Reference, whole capture and chunk-by-chunk: the same scans and counts."""
    reader = CaptureReader(path)
    reference = ReferenceDecoder(measuring_mode, limits)
    expected = reference.decode(reader)
    want = counters(reference, reader)

    reader = CaptureReader(path)
    whole = ScanDecoder(measuring_mode, limits)
    got = whole.feed_stream(reader.stream()) + whole.close()
    assert_same_scans(got, expected)
    assert counters(whole, reader) == want

    reader = CaptureReader(path)
    streamed = ScanDecoder(measuring_mode, limits)
    got = [s for stamp, chunk in reader.chunks() for s in streamed.feed(chunk, stamp)]
    got += streamed.close()
    assert_same_scans(got, expected)
    assert counters(streamed, reader) == want

    # received in batches of chunks (the mission loop's and a robot agent's way), 7 at a time
    reader = CaptureReader(path)
    chunks = list(reader.chunks())
    batched = ScanDecoder(measuring_mode, limits)
    got = [s for k in range(0, len(chunks), 7) for s in batched.feed_chunks(chunks[k : k + 7])]
    got += batched.feed_chunks([]) + batched.close()
    assert_same_scans(got, expected)
    assert counters(batched, reader) == want
    return expected


def test_a_clean_capture_decodes_as_the_reference_does(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    path = write_capture(tmp_path / "a.cap", ["good"] * 300, rng)
    scans = assert_all_agree(path, 1, LIMITS)
    assert len(scans) == 300
    assert sum(np.isnan(s.ranges_m).any() for s in scans) > 250


def test_every_rule_and_malformation_is_counted_as_the_reference_counts(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    kinds = ["good"] * 40
    for odd in ODD:
        kinds += [odd, "good", "good", "good"]
    path = write_capture(tmp_path / "a.cap", kinds, rng)
    assert_all_agree(path, 1, LIMITS)
    reader = CaptureReader(path)
    decoder = ScanDecoder(1, LIMITS)
    scans = decoder.feed_stream(reader.stream())
    assert decoder.check is not None
    # Each rule fired (the test can tell a decoder that skips one from the reference); mode 1
    # uses every bit, so only mode 15 has flag bits to break (below).
    assert set(decoder.check.rejected) == {"range", "status", "sequence", "unit", "count"}
    assert decoder.stats.undecodable == 4  # count, short, size, reserved unit
    assert decoder.stats.acks == 1
    assert len(scans) == decoder.check.accepted


@pytest.mark.parametrize("measuring_mode", [1, 3, 15])
def test_other_measuring_modes_and_no_limits_agree(tmp_path: Path, measuring_mode: int) -> None:
    rng = np.random.default_rng(measuring_mode)
    path = write_capture(tmp_path / "a.cap", [*ODD, *["good"] * 30, *ODD], rng)
    assert_all_agree(path, measuring_mode, LIMITS)
    assert_all_agree(path, measuring_mode, None)
    decoder = ScanDecoder(measuring_mode, LIMITS)
    decoder.feed_stream(CaptureReader(path).stream())
    assert decoder.check is not None
    assert ("flags" in decoder.check.rejected) == (measuring_mode == 15)


def test_a_plain_dump_is_decoded_but_yields_no_scans(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    dump = tmp_path / "a.bin"
    dump.write_bytes(b"".join(telegram("good", k, rng) for k in range(400)))  # > 64 KiB
    assert assert_all_agree(dump, 1, LIMITS) == []
    decoder = ScanDecoder(1, LIMITS)
    decoder.feed_stream(CaptureReader(dump).stream())
    assert decoder.stats.decoded == 400


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    kinds=st.lists(st.sampled_from(("good",) * 8 + ODD), min_size=1, max_size=60),
    seed=st.integers(0, 2**32 - 1),
    flips=st.integers(0, 12),
    inserts=st.integers(0, 4),
    cut=st.integers(0, 300),
)
def test_corrupted_captures_decode_as_the_reference_does(
    tmp_path: Path, kinds: list[str], seed: int, flips: int, inserts: int, cut: int
) -> None:
    rng = np.random.default_rng(seed)
    path = tmp_path / f"{seed}.cap"
    path.unlink(missing_ok=True)
    write_capture(path, kinds, rng)
    spoil(path, rng, flips, inserts, cut)
    assert_all_agree(path, 1, LIMITS)


def test_decoding_a_chunk_never_depends_on_what_came_in_the_same_call(tmp_path: Path) -> None:
    """Fed the stream in one call or its records one by one, a held incomplete frame is
    judged at the same chunk boundaries: same scans, same stamps."""
    rng = np.random.default_rng(4)
    path = write_capture(tmp_path / "a.cap", ["good", "garbage"] * 50, rng)
    stream = CaptureReader(path).stream()
    assert len(stream.ends) > 100
    one = ScanDecoder(1, LIMITS)
    many = ScanDecoder(1, LIMITS)
    starts = [0, *stream.ends[:-1].tolist()]
    pieces = [
        many.feed(stream.data[a:b].tobytes(), float(stamp))
        for a, b, stamp in zip(starts, stream.ends.tolist(), stream.stamps_s, strict=True)
    ]
    assert_same_scans(one.feed_stream(stream), [s for p in pieces for s in p])
    assert one.stats == many.stats
