"""The LMS 200 protocol: verified telegrams bit-exact, decoding, and a parser that never breaks."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sensors.lms200.protocol.commands import (
    LmsConfig,
    cmd_continuous,
    cmd_installation_mode,
    cmd_permanent_baud,
    cmd_read_config,
    cmd_request_errors,
    cmd_request_scan,
    cmd_request_status,
    cmd_request_type,
    cmd_reset,
    cmd_set_baud,
    cmd_stop,
    cmd_variant,
    cmd_write_config,
)
from sensors.lms200.protocol.replies import (
    ConfigReply,
    IncorrectCommand,
    ModeReply,
    PowerOn,
    Reply,
    ResetAck,
    StatusReply,
    TypeReply,
    VariantReply,
    decode_reply,
    encode_config_reply,
    encode_mode_reply,
    encode_status_reply,
    encode_variant_reply,
)
from sensors.lms200.protocol.scan import (
    Scan,
    SpecialCode,
    decode_scan,
    encode_scan,
    scan_interval_s,
)
from sensors.lms200.protocol.stream import Handshake, StreamParser, Telegram
from sensors.lms200.protocol.telegram import MAX_LEN, ProtocolError, checksum, frame, reply_frame


def h(text: str) -> bytes:
    return bytes.fromhex(text)


#: Every verified telegram of docs/lms200-protocol.md §3.3–3.4 and the encoder that builds it.
VERIFIED = [
    ("02 00 01 00 31 15 12", cmd_request_status()),
    ("02 00 0A 00 20 00 53 49 43 4B 5F 4C 4D 53 BE C5", cmd_installation_mode("SICK_LMS")),
    ("02 80 03 00 A0 00 10 16 0A", encode_mode_reply(0)),
    ("02 00 05 00 3B B4 00 32 00 3B 1F", cmd_variant(180, 0.5)),
    ("02 80 07 00 BB 01 B4 00 32 00 10 03 9D", encode_variant_reply(True, 180, 0.5)),
    ("02 00 02 00 30 01 31 18", cmd_request_scan(0x01)),
    ("02 00 01 00 10 34 12", cmd_reset()),
    ("02 00 01 00 32 16 12", cmd_request_errors()),
    ("02 00 01 00 3A 1E 12", cmd_request_type()),
    ("02 00 01 00 74 50 12", cmd_read_config()),
    ("02 00 02 00 20 24 34 08", cmd_continuous()),
    ("02 00 02 00 20 25 35 08", cmd_stop()),
    ("02 00 02 00 20 40 50 08", cmd_set_baud(38400)),
    ("02 00 02 00 20 41 51 08", cmd_set_baud(19200)),
    ("02 00 02 00 20 42 52 08", cmd_set_baud(9600)),
    ("02 00 02 00 20 48 58 08", cmd_set_baud(500000)),
    ("02 00 05 00 3B 64 00 64 00 1D 0F", cmd_variant(100, 1.0)),
    ("02 00 05 00 3B 64 00 32 00 B1 59", cmd_variant(100, 0.5)),
    ("02 00 05 00 3B 64 00 19 00 E7 72", cmd_variant(100, 0.25)),
    ("02 00 05 00 3B B4 00 64 00 97 49", cmd_variant(180, 1.0)),
    ("02 00 05 00 3B B4 00 32 00 3B 1F", cmd_variant(180, 0.5)),
    ("02 00 02 00 66 01 9D 4E", cmd_permanent_baud(True)),
    ("02 00 02 00 66 00 9C 4E", cmd_permanent_baud(False)),
    ("02 80 02 00 91 10 79 30", reply_frame(0x91)),
    ("02 80 02 00 92 10 7F 33", reply_frame(0x92)),
    (
        "02 80 17 00 BA 4C 4D 53 32 30 30 3B 33 30 31 30 36 33 3B 56 30 32 2E 31 30 20 10 22 61",
        reply_frame(0xBA, b"LMS200;301063;V02.10 "),
    ),
    (
        "02 80 17 00 90 4C 4D 53 32 30 30 3B 33 30 31 30 36 33 3B 56 30 32 2E 31 30 20 10 63 5E",
        reply_frame(0x90, b"LMS200;301063;V02.10 "),
    ),
    (
        "02 00 23 00 77 00 00 46 00 00 00 01 00 00 02 02 02 00 00 0A 0A 50 64 00 0A 0A 50 80 00"
        " 0A 0A 50 64 00 00 00 00 02 00 7B 4B",
        cmd_write_config(LmsConfig.factory()),
    ),
]


@pytest.mark.parametrize(("expected", "encoded"), VERIFIED)
def test_verified_telegrams_encode_bit_exactly(expected: str, encoded: bytes) -> None:
    assert encoded == h(expected)


@pytest.mark.parametrize(("expected", "encoded"), VERIFIED)
def test_verified_telegrams_round_trip_through_the_parser(expected: str, encoded: bytes) -> None:
    parser = StreamParser("any")
    events = parser.feed(h(expected))
    assert len(events) == 1
    telegram = events[0]
    assert isinstance(telegram, Telegram)
    assert telegram.raw == h(expected)
    assert telegram.offset == 0
    assert parser.stats.bytes_skipped == 0
    assert parser.pending == 0


def test_checksum_vectors_and_not_a_library_crc() -> None:
    assert checksum(h("02 00 01 00 31")) == 0x1215
    assert checksum(h("02 00 0A 00 20 00 53 49 43 4B 5F 4C 4D 53")) == 0xC5BE
    assert checksum(h("02 80 03 00 A0 00 10")) == 0x0A16
    # CRC-16/BUYPASS over the same bytes would be 0x8041 (§3.2).
    assert checksum(h("02 00 01 00 31")) != 0x8041
    assert checksum(b"") == 0


def test_manual_misprints_are_rejected_as_bad_checksums() -> None:
    parser = StreamParser("any")
    # Table 6-4 prints `5F B2` for the installation-mode telegram; the correct value is `BE C5`.
    assert parser.feed(h("02 00 0A 00 20 00 53 49 43 4B 5F 4C 4D 53 5F B2")) == []
    assert parser.stats.checksum_failures == 1


def test_decode_replies() -> None:
    def decoded(raw: bytes) -> Reply:
        (telegram,) = StreamParser().feed(raw)
        assert isinstance(telegram, Telegram)
        return decode_reply(telegram)

    mode = decoded(encode_mode_reply(1))
    assert isinstance(mode, ModeReply)
    assert not mode.ok
    assert mode.result == 1
    variant = decoded(encode_variant_reply(True, 100, 0.25))
    assert isinstance(variant, VariantReply)
    assert (variant.ok, variant.angle_deg, variant.resolution_deg) == (True, 100, 0.25)
    kind = decoded(reply_frame(0xBA, b"LMS200;301063;V02.10 "))
    assert isinstance(kind, TypeReply)
    assert kind.text == "LMS200;301063;V02.10 "
    power = decoded(reply_frame(0x90, b"LMS200;301063;V02.10 "))
    assert isinstance(power, PowerOn)
    assert power.text.startswith("LMS200")
    assert isinstance(decoded(reply_frame(0x91)), ResetAck)
    assert isinstance(decoded(reply_frame(0x92)), IncorrectCommand)
    config = LmsConfig.factory().with_changes(measuring_mode=1, realtime_indices=True)
    read = decoded(encode_config_reply(config))
    assert isinstance(read, ConfigReply)
    assert read.config == config
    assert read.config.realtime_indices
    written = decoded(encode_config_reply(config, write_result=False))
    assert isinstance(written, ConfigReply)
    assert written.name == "config_write"
    assert not written.ok
    status = decoded(
        encode_status_reply(angle_deg=100, resolution_deg=1.0, baud_rate=38400, measuring_mode=1)
    )
    assert isinstance(status, StatusReply)
    assert (status.angle_deg, status.resolution_deg, status.baud_rate) == (100, 1.0, 38400)
    assert status.measuring_mode == 1
    assert status.version == "V02.10 "
    generic = decoded(reply_frame(0xB2, b"\x00\x00"))
    assert type(generic) is Reply


def test_decode_reply_rejects_short_and_misrouted_replies() -> None:
    (short,) = StreamParser().feed(reply_frame(0xBB, b"\x01"))
    assert isinstance(short, Telegram)
    with pytest.raises(ProtocolError, match=r"variant reply \(0xbb\) too short: 1 bytes"):
        decode_reply(short)
    (scan,) = StreamParser().feed(encode_scan(np.ones(101)))
    assert isinstance(scan, Telegram)
    with pytest.raises(ProtocolError, match="decode it with decode_scan"):
        decode_reply(scan)


def test_config_block_fields() -> None:
    factory = LmsConfig.factory()
    assert factory.measuring_mode == 0
    assert factory.unit_mm
    assert not factory.realtime_indices
    changed = factory.with_changes(measuring_mode=1, unit_mm=False, realtime_indices=True)
    assert (changed.measuring_mode, changed.unit_mm, changed.realtime_indices) == (1, False, True)
    assert changed.with_changes(realtime_indices=False).raw[4] == factory.raw[4]
    assert changed.raw[7:] == factory.raw[7:]
    with pytest.raises(ProtocolError, match="34 bytes, got 33"):
        LmsConfig(factory.raw[:33])
    with pytest.raises(ProtocolError, match="unknown measuring mode 9"):
        factory.with_changes(measuring_mode=9)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: cmd_set_baud(115200), r"talks at \(9600, 19200, 38400, 500000\) Bd, not 115200"),
        (lambda: cmd_variant(180, 0.25), r"no LMS 200 variant 180°/0\.25°"),
        (lambda: cmd_installation_mode("SHORT"), r"8 ASCII characters, got 'SHORT'"),
        (lambda: frame(0x90), r"host command codes are 00-8F, got 0x90"),
        (lambda: reply_frame(0x10), r"reply codes are 90-FF, got 0x10"),
        (lambda: frame(0x20, bytes(900)), r"telegram body must be 1-812 bytes, got 901"),
        (lambda: frame(0x20, addr=300), r"address must be 0-255, got 300"),
        (lambda: StreamParser("sideways"), r"direction must be one of"),
    ],
)  # fmt: skip
def test_encoding_errors(call, message: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ProtocolError, match=message):
        call()


# --------------------------------------------------------------------------------------------
# Measured values


def test_scan_round_trip_with_flags_special_codes_and_indices() -> None:
    rng = np.random.default_rng(1)
    ranges = rng.uniform(0.1, 8.0, 101)
    ranges[[3, 50]] = np.nan
    codes = np.zeros(101, dtype=np.uint8)
    codes[10] = SpecialCode.DAZZLE
    codes[11] = SpecialCode.OUT_OF_RANGE
    flags = rng.integers(0, 8, 101)
    raw = encode_scan(ranges, flags=flags, codes=codes, scan_index=200, telegram_index=7)
    (telegram,) = StreamParser().feed(raw)
    assert isinstance(telegram, Telegram)
    scan = decode_scan(telegram, measuring_mode=1)
    valid = np.isfinite(ranges) & (codes == 0)
    np.testing.assert_allclose(
        scan.ranges_m[valid], np.round(ranges[valid] * 1000) / 1000, atol=1e-12
    )
    assert np.isnan(scan.ranges_m[~valid]).all()
    assert scan.code[3] == SpecialCode.NO_RETURN
    assert scan.code[10] == SpecialCode.DAZZLE
    assert scan.code[11] == SpecialCode.OUT_OF_RANGE
    np.testing.assert_array_equal(scan.flags, flags)
    np.testing.assert_array_equal(scan.reflector, flags > 0)
    assert (scan.scan_index, scan.telegram_index, scan.status) == (200, 7, 0x10)
    assert scan.unit_m == 0.001
    # 100° variant: −50° … +50° in the scanner frame (the LMS's own 40° … 140°).
    assert math.degrees(scan.bearing_rad[0]) == pytest.approx(-50.0)
    assert math.degrees(scan.bearing_rad[-1]) == pytest.approx(50.0)


def test_a_decoded_scan_is_the_scan_its_fields_make() -> None:
    """Decoded scans are made with their slots set directly: the same as ``Scan(...)`` of
    their fields, frozen, equal and hashable as dataclasses are, and ``replace`` works."""
    raw = encode_scan(np.linspace(0.5, 4.0, 181), scan_index=3, telegram_index=4)
    (telegram,) = StreamParser().feed(raw)
    assert isinstance(telegram, Telegram)
    scan = decode_scan(telegram, measuring_mode=1)
    names = [f.name for f in dataclasses.fields(Scan)]
    made = Scan(*(getattr(scan, name) for name in names))
    assert type(scan) is Scan
    assert all(getattr(made, name) is getattr(scan, name) for name in names)
    assert scan == made
    assert hash(dataclasses.replace(scan, ranges_m=None, bearing_rad=None, flags=None,
                                    code=None, raw=None)) is not None  # fmt: skip
    with pytest.raises(dataclasses.FrozenInstanceError):
        scan.unit_m = 1.0  # type: ignore[misc]
    stamped = scan.with_stamp(12.5)
    assert (stamped.stamp_s, stamped.count_word, stamped.scan_index) == (12.5, scan.count_word, 3)


@pytest.mark.parametrize(
    ("count", "first_deg", "step_deg"),
    [(101, -50, 1.0), (201, -50, 0.5), (401, -50, 0.25), (181, -90, 1.0), (361, -90, 0.5)],
)
def test_scan_bearings_per_variant(count: int, first_deg: float, step_deg: float) -> None:
    (telegram,) = StreamParser().feed(encode_scan(np.full(count, 2.0)))
    assert isinstance(telegram, Telegram)
    scan = decode_scan(telegram)
    np.testing.assert_allclose(
        np.degrees(scan.bearing_rad), first_deg + step_deg * np.arange(count)
    )


@pytest.mark.parametrize(
    ("mode", "mask", "shift", "max_flag"),
    [(0, 0x1FFF, 13, 7), (3, 0x3FFF, 14, 3), (5, 0x7FFF, 15, 1), (15, 0x7FFF, 16, 0)],
)
def test_measuring_modes_split_distance_and_flags(
    mode: int, mask: int, shift: int, max_flag: int
) -> None:
    ranges = np.linspace(0.5, 7.5, 101)
    flags = np.arange(101) % (max_flag + 1)
    (telegram,) = StreamParser().feed(encode_scan(ranges, flags=flags, measuring_mode=mode))
    assert isinstance(telegram, Telegram)
    scan = decode_scan(telegram, measuring_mode=mode)
    np.testing.assert_allclose(scan.ranges_m, np.round(ranges * 1000) / 1000)
    np.testing.assert_array_equal(scan.flags, flags)
    assert (scan.raw & mask == np.round(ranges * 1000)).all()
    assert scan.reflector.any() == (mode in (3, 5))


def test_special_codes_are_never_ranges() -> None:
    raw = np.array([0x1FFF, 0x1FFE, 0x1FFD, 0x1FFB, 0x1FFA, 0x1FF7, 0x1FF8, 0x1FF6] + [100] * 93)
    data = (0x4000 | 101).to_bytes(2, "little") + raw.astype("<u2").tobytes()
    telegram = Telegram(0, 0x80, 0xB0, data, 0x10)
    scan = decode_scan(telegram, measuring_mode=0)
    assert scan.code[:8].tolist() == [
        SpecialCode.NO_RETURN, SpecialCode.DAZZLE, SpecialCode.OVERFLOW,
        SpecialCode.SIGNAL_TO_NOISE, SpecialCode.CHANNEL_ERROR, SpecialCode.OUT_OF_RANGE,
        SpecialCode.UNDOCUMENTED, SpecialCode.VALID,
    ]  # fmt: skip
    assert np.isnan(scan.ranges_m[:7]).all()
    assert scan.ranges_m[7] == pytest.approx(0x1FF6 / 1000)  # the largest real distance


def test_centimetre_unit_and_partial_scans() -> None:
    (telegram,) = StreamParser().feed(encode_scan(np.full(181, 25.0), unit_mm=False))
    assert isinstance(telegram, Telegram)
    scan = decode_scan(telegram, measuring_mode=1)
    assert scan.unit_m == 0.01
    np.testing.assert_allclose(scan.ranges_m, 25.0)
    # 0x68B4: 180 values, mm, partial scan at x.25° (§6.3 example).
    data = (0x68B4).to_bytes(2, "little") + np.full(180, 1000, "<u2").tobytes()
    partial = decode_scan(Telegram(0, 0x80, 0xB0, data, 0x10))
    assert partial.partial
    assert partial.partial_offset_deg == 0.25
    assert math.degrees(partial.bearing_rad[0]) == pytest.approx(-89.75)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ((0x4000 | 101).to_bytes(2, "little") + bytes(200), r"announces 101 values but carries 200 bytes"),
        ((0x4000 | 99).to_bytes(2, "little") + bytes(198), r"has 101, 201, 401, 181 or 361 values, got 99"),
        ((0x8000 | 101).to_bytes(2, "little") + bytes(202), r"reserved unit code 2"),
        (b"\x01", r"B0 reply too short"),
    ],
)  # fmt: skip
def test_malformed_scans_are_clear_errors(data: bytes, message: str) -> None:
    with pytest.raises(ProtocolError, match=message):
        decode_scan(Telegram(0, 0x80, 0xB0, data, 0x10))


def test_decode_scan_rejects_other_replies_and_modes() -> None:
    with pytest.raises(ProtocolError, match="not a measured-values reply"):
        decode_scan(Telegram(0, 0x80, 0xA0, b"\x00", 0x10))
    telegram = Telegram(0, 0x80, 0xB0, (0x4000 | 101).to_bytes(2, "little") + bytes(202), 0x10)
    with pytest.raises(ProtocolError, match="unknown measuring mode 9"):
        decode_scan(telegram, measuring_mode=9)


@pytest.mark.parametrize(
    ("baud", "count", "resolution", "rate_hz"),
    [
        (38400, 101, 1.0, 12.5), (9600, 101, 1.0, 4.2), (19200, 101, 1.0, 7.5),
        (500000, 101, 1.0, 75.0), (38400, 181, 1.0, 8.3), (9600, 361, 0.5, 1.3),
        (38400, 401, 0.25, 3.8), (500000, 361, 0.5, 37.5),
    ],
)  # fmt: skip
def test_scan_rates_match_the_manual(
    baud: int, count: int, resolution: float, rate_hz: float
) -> None:
    interval = scan_interval_s(baud, count, resolution, indices=False)
    assert 1.0 / interval == pytest.approx(rate_hz, abs=0.08)  # the manual rounds 75.08 to 75


# --------------------------------------------------------------------------------------------
# The stream parser


def test_parser_resyncs_after_garbage_bad_checksum_truncation_and_absurd_length() -> None:
    good = [
        encode_mode_reply(0),
        encode_scan(np.full(101, 1.5)),
        encode_variant_reply(True, 100, 1.0),
    ]
    corrupt = bytearray(good[1])
    corrupt[40] ^= 0xFF  # bad checksum
    stream = (
        b"\x02\x80\xff\xff garbage"  # absurd length
        + good[0]
        + bytes(corrupt)
        + good[1][:57]  # truncated: the next frame starts inside it
        + good[1]
        + b"\x02\x80"  # a lone header
        + good[2]
    )
    parser = StreamParser()
    telegrams = [e for e in parser.feed(stream) if isinstance(e, Telegram)]
    assert [t.raw for t in telegrams] == [good[0], good[1], good[2]]
    assert parser.stats.telegrams == 3
    assert parser.stats.checksum_failures >= 2
    assert parser.stats.bytes_skipped == len(stream) - sum(len(g) for g in good)


def test_bytes_inside_a_frame_with_a_bad_checksum_are_not_handshakes() -> None:
    reply = encode_mode_reply(0)
    payload = bytes([0x06, 0x15] * 20)  # what would read as ACK, NAK, ACK, … outside a frame
    corrupt = bytearray(reply_frame(0xB0, payload))
    corrupt[-1] ^= 0xFF  # bad checksum
    stream = bytes(corrupt) + b"\x06" + reply + b"\x15"
    parser = StreamParser()
    events = parser.feed(stream)
    handshakes = [e for e in events if isinstance(e, Handshake)]
    assert [(h.ack, h.offset) for h in handshakes] == [
        (True, len(corrupt)),
        (False, len(stream) - 1),
    ]
    assert [e.raw for e in events if isinstance(e, Telegram)] == [reply]
    assert (parser.stats.acks, parser.stats.naks, parser.stats.checksum_failures) == (1, 1, 1)
    assert parser.stats.bytes_skipped == len(corrupt)


def test_random_bytes_hold_no_more_handshakes_than_their_lone_06_and_15() -> None:
    data = np.random.default_rng(7).integers(0, 256, 200_000, dtype=np.uint8).tobytes()
    parser = StreamParser()
    handshakes = sum(isinstance(e, Handshake) for e in parser.feed(data) + parser.close())
    assert handshakes <= data.count(b"\x06") + data.count(b"\x15")
    assert handshakes == parser.stats.acks + parser.stats.naks


def test_a_false_start_does_not_hold_back_a_reply() -> None:
    # A stray `02 80` with a plausible length (515) before a complete reply: the reply must be
    # delivered now — a driver waiting for it would otherwise time out — and at end of stream.
    reply = encode_mode_reply(0)
    parser = StreamParser()
    events = parser.feed(b"\x02\x80\x03\x02" + reply)
    assert [e.raw for e in events if isinstance(e, Telegram)] == [reply]
    assert parser.pending == 0
    held = StreamParser()
    assert held.feed(b"\x02\x80\x03\x02" + reply[:6]) == []
    assert [e.raw for e in held.feed(reply[6:]) if isinstance(e, Telegram)] == [reply]


def test_close_rescans_what_it_holds() -> None:
    reply = encode_mode_reply(0)
    parser = StreamParser()
    parser.feed(b"\x02\x80\xff\x01" + reply[:-1])  # false start, then a truncated reply
    assert parser.close() == []
    assert parser.stats.bytes_skipped == 4 + len(reply) - 1


def test_parser_handles_one_byte_chunks_and_reports_offsets() -> None:
    frames = [encode_mode_reply(0), b"\x06", encode_scan(np.full(101, 2.0))]
    stream = b"".join(frames)
    parser = StreamParser()
    events = []
    for k in range(len(stream)):
        events += parser.feed(stream[k : k + 1], stamp_s=float(k))
        assert parser.pending <= MAX_LEN + 6
    assert [type(e) for e in events] == [Telegram, Handshake, Telegram]
    assert [e.offset for e in events] == [0, 9, 10]
    assert events[2].stamp_s == len(stream) - 1  # the chunk that completed it
    assert isinstance(events[1], Handshake)
    assert events[1].ack


def test_parser_direction_filters_and_close_counts_the_remainder() -> None:
    command, reply = cmd_stop(), encode_mode_reply(0)
    to_sensor = StreamParser("to_sensor")
    assert [t.raw for t in to_sensor.feed(command + reply) if isinstance(t, Telegram)] == [command]
    from_sensor = StreamParser("from_sensor")
    assert [t.raw for t in from_sensor.feed(command + reply) if isinstance(t, Telegram)] == [reply]
    from_sensor.feed(reply[:5])
    assert from_sensor.pending == 5
    assert from_sensor.close() == []
    assert from_sensor.pending == 0
    assert from_sensor.stats.bytes_skipped == len(command) + 5


@st.composite
def telegram_streams(draw: st.DrawFn) -> tuple[list[bytes], bytes, list[int]]:
    """Random valid replies interleaved with garbage and corrupted copies of replies."""
    telegrams: list[bytes] = []
    pieces: list[bytes] = []
    for _ in range(draw(st.integers(0, 8))):
        kind = draw(st.sampled_from(["scan", "mode", "variant", "type"]))
        if kind == "scan":
            count = draw(st.sampled_from([101, 181]))
            values = draw(st.lists(st.floats(0.0, 8.0), min_size=count, max_size=count))
            raw = encode_scan(
                np.array(values), flags=np.zeros(count), scan_index=draw(st.integers(0, 255))
            )
        elif kind == "mode":
            raw = encode_mode_reply(draw(st.integers(0, 2)))
        elif kind == "variant":
            raw = encode_variant_reply(draw(st.booleans()), 100, 1.0)
        else:
            raw = reply_frame(0xBA, draw(st.binary(min_size=0, max_size=40)))
        noise = draw(st.binary(max_size=30).filter(lambda b: b"\x06" not in b and b"\x15" not in b))
        action = draw(st.sampled_from(["keep", "corrupt", "truncate"]))
        if action == "keep":
            pieces += [noise, raw]
            telegrams.append(raw)
        elif action == "corrupt":
            position = draw(st.integers(4, len(raw) - 1))
            damaged = bytearray(raw)
            damaged[position] ^= draw(st.integers(1, 255))
            pieces += [noise, bytes(damaged)]
        else:
            pieces += [noise, raw[: draw(st.integers(1, len(raw) - 1))]]
    stream = b"".join(pieces)
    cuts = sorted(draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    return telegrams, stream, cuts


@settings(max_examples=150, deadline=None)
@given(telegram_streams())
def test_parser_recovers_every_telegram_and_invents_none(
    case: tuple[list[bytes], bytes, list[int]],
) -> None:
    telegrams, stream, cuts = case
    parser = StreamParser()
    found: list[bytes] = []
    bounds = [0, *cuts, len(stream)]
    for start, stop in itertools.pairwise(bounds):
        found += [e.raw for e in parser.feed(stream[start:stop]) if isinstance(e, Telegram)]
        assert parser.pending <= MAX_LEN + 6
    found += [e.raw for e in parser.close() if isinstance(e, Telegram)]
    # Every intact telegram is recovered in order; anything else found must be a checksum-valid
    # frame that lay verbatim in the stream (a corruption can leave one), never a fabrication.
    it = iter(found)
    assert all(any(f == t for f in it) for t in telegrams)
    assert all(f in stream for f in found)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=3000), st.integers(1, 64))
def test_parser_never_raises_and_stays_bounded(data: bytes, chunk: int) -> None:
    parser = StreamParser("any")
    for start in range(0, len(data), chunk):
        for event in parser.feed(data[start : start + chunk]):
            if isinstance(event, Telegram):
                assert event.raw in data
        assert parser.pending <= MAX_LEN + 6
    parser.close()
    stats = parser.stats
    assert stats.bytes_in == len(data)
    assert stats.bytes_skipped + stats.acks + stats.naks <= len(data)


def test_scans_of_one_variant_share_one_read_only_bearing_array() -> None:
    (one,) = StreamParser().feed(encode_scan(np.full(101, 2.0)))
    (two,) = StreamParser().feed(encode_scan(np.full(101, 3.0)))
    assert isinstance(one, Telegram)
    assert isinstance(two, Telegram)
    first, second = decode_scan(one), decode_scan(two)
    assert first.bearing_rad is second.bearing_rad
    assert not first.bearing_rad.flags.writeable
    np.testing.assert_allclose(np.degrees(first.bearing_rad[[0, 50, 100]]), [-50.0, 0.0, 50.0])
