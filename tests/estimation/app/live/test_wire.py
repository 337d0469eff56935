"""The wire format: chunks, payloads and JSON messages round-trip; anything else is a WireError."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.app.live.session import check_endpoint
from estimation.app.live.wire import (
    MAGIC,
    MAX_CHUNK,
    Chunk,
    WireError,
    chunk_key,
    decode_chunk,
    decode_json,
    decode_lms,
    decode_odometry,
    encode_chunk,
    encode_json,
    encode_lms,
    encode_odometry,
    mission_key,
    parse_chunk_key,
)

CHUNK = Chunk("essex_lab", "ab12cd34", "a", "lms", 7, b"\x02\x80payload")


def test_a_chunk_round_trips() -> None:
    assert decode_chunk(encode_chunk(CHUNK)) == CHUNK


@given(st.binary(max_size=2000), st.integers(0, 10**9), st.sampled_from(["lms", "odom", "event"]))
@settings(max_examples=60, deadline=None)
def test_any_payload_round_trips(payload: bytes, seq: int, stream: str) -> None:
    chunk = Chunk("m", "r1", "b", stream, seq, payload)
    assert decode_chunk(encode_chunk(chunk)) == chunk


@given(st.binary(max_size=400))
@settings(max_examples=200, deadline=None)
def test_random_bytes_never_decode_silently(data: bytes) -> None:
    with pytest.raises(WireError):
        decode_chunk(data)


def _with_header(header: object, payload: bytes = b"xy") -> bytes:
    return MAGIC + json.dumps(header).encode() + b"\n" + payload


GOOD = {"mission": "m", "run": "r", "robot": "a", "stream": "lms", "seq": 0, "size": 2,
        "crc32": zlib.crc32(b"xy")}  # fmt: skip


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"COOPMAP-LMSCAP 1\n{}", "no magic"),
        (MAGIC + b"x" * 5000, "no end of line"),
        (MAGIC + b"{not json\n", "not JSON"),
        (MAGIC + b"\xff\xfe\n", "not JSON"),
        (_with_header([1, 2]), "not a JSON object"),
        (_with_header({**GOOD, "seq": "0"}), "'seq' missing or not int"),
        (_with_header({**GOOD, "seq": True}), "'seq' missing or not int"),
        (_with_header({k: v for k, v in GOOD.items() if k != "crc32"}), "'crc32' missing"),
        (_with_header({**GOOD, "stream": "video"}), "stream 'video'"),
        (_with_header({**GOOD, "robot": "AB"}), "robot 'AB'"),
        (_with_header({**GOOD, "seq": -1}), "payload bytes"),
        (_with_header({**GOOD, "size": 3}), "header says 3"),
        (_with_header({**GOOD, "crc32": 1}), "CRC-32 mismatch"),
    ],
)
def test_malformed_chunks_are_one_line_errors(data: bytes, message: str) -> None:
    with pytest.raises(WireError, match=message) as info:
        decode_chunk(data)
    assert "\n" not in str(info.value)


def test_an_oversized_chunk_is_refused_before_it_is_read() -> None:
    with pytest.raises(WireError, match="at most"):
        decode_chunk(b"\0" * (MAX_CHUNK + 1))


def test_lms_records_round_trip_and_cut_records_fail() -> None:
    records = [(0.5, b"\x02\x80abc"), (0.51, b""), (1e6, bytes(range(256)))]
    data = encode_lms(records)
    assert decode_lms(data) == records
    with pytest.raises(WireError, match="cut short"):
        decode_lms(data[:-1])
    with pytest.raises(WireError, match="cut short"):
        decode_lms(data[:5])
    with pytest.raises(WireError, match="not finite"):
        decode_lms(encode_lms([(float("nan"), b"x")]))


def test_odometry_round_trips_and_bad_rows_fail() -> None:
    times = np.array([0.0, 0.1, 0.2])
    poses = np.array([[1.0, 2.0, 0.1], [1.1, 2.0, 0.1], [1.2, 2.1, 0.2]])
    t, p = decode_odometry(encode_odometry(times, poses))
    np.testing.assert_array_equal(t, times)
    np.testing.assert_array_equal(p, poses)
    with pytest.raises(WireError, match="whole number of rows"):
        decode_odometry(encode_odometry(times, poses)[:-8])
    with pytest.raises(WireError, match="not finite"):
        decode_odometry(encode_odometry(np.array([np.inf]), poses[:1]))


def test_json_messages() -> None:
    assert decode_json(encode_json({"seq": 3}), "reply") == {"seq": 3}
    for bad, message in [(None, "empty"), (b"[1]", "not a JSON object"), (b"{", "not JSON"),
                         (b"\xff", "not JSON"), (b" " * (1 << 23), "bytes of JSON")]:  # fmt: skip
        with pytest.raises(WireError, match=message):
            decode_json(bad, "reply")
    with pytest.raises(ValueError, match="not JSON compliant"):
        encode_json({"x": float("nan")})


def test_keys() -> None:
    key = chunk_key("essex_lab", "b", "odom", 12)
    assert key == "coopmap/essex_lab/robot/b/odom/12"
    assert parse_chunk_key(key, "essex_lab") == ("b", "odom", 12)
    for foreign in ["coopmap/other/robot/b/odom/12", "coopmap/essex_lab/robot/b/odom/x",
                    "coopmap/essex_lab/robot/B/odom/1", "coopmap/essex_lab/robot/b/tf/1",
                    "coopmap/essex_lab/robot/b/cmd", "coopmap/essex_lab/base/map"]:  # fmt: skip
        assert parse_chunk_key(foreign, "essex_lab") is None
    with pytest.raises(WireError, match="mission name"):
        mission_key("a/b")
    with pytest.raises(WireError, match="mission name"):
        mission_key("")


def test_endpoints() -> None:
    assert check_endpoint("tcp/127.0.0.1:7447") == "tcp/127.0.0.1:7447"
    assert check_endpoint("tcp/[::1]:7447") == "tcp/[::1]:7447"
    assert check_endpoint("tcp/robot-base.local:80") == "tcp/robot-base.local:80"
    for bad in ["127.0.0.1:7447", "tcp/127.0.0.1", "tcp/127.0.0.1:0", "tcp/127.0.0.1:70000",
                "http/x:1", "tcp/a b:1"]:  # fmt: skip
        with pytest.raises(WireError, match="expected PROTOCOL/HOST:PORT"):
            check_endpoint(bad)


def test_a_journal_cut_short_loses_only_its_last_line(tmp_path: Path) -> None:
    from estimation.app.live.wire import append_journal, read_journal

    path = tmp_path / "commands.jsonl"
    assert read_journal(path) == []
    append_journal(path, {"seq": 0})
    append_journal(path, {"seq": 1})
    with open(path, "ab") as f:
        f.write(b'{"seq": 2, "op": "mo')  # killed while writing
    assert read_journal(path) == [{"seq": 0}, {"seq": 1}]
    append_journal(path, {"seq": 2})  # the next line starts on a line of its own
    assert read_journal(path) == [{"seq": 0}, {"seq": 1}, {"seq": 2}]
    path.write_bytes(b'{"seq": 0}\n[1, 2]\n{"seq": 1}\n')
    assert read_journal(path) == [{"seq": 0}]
