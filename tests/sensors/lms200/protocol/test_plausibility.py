"""Plausibility of checksum-valid scans: each rule on crafted telegrams, and what it catches."""

from __future__ import annotations

import json
import struct
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from estimation.app.cli.main import app
from sensors.geometry.frames import scanner_pose_matrix
from sensors.lms200.capture import CaptureReader, CaptureWriter, decode_stream
from sensors.lms200.protocol.plausibility import Implausible, ScanCheck, ScanLimits
from sensors.lms200.protocol.scan import Scan, decode_scan, encode_scan
from sensors.lms200.protocol.stream import StreamParser, Telegram
from sensors.lms200.protocol.telegram import (
    TURN_S,
    ProtocolError,
    checksum,
    checksum_kernel,
    reply_frame,
)
from sensors.scan3d.mirror import MirrorGeometry
from sensors.sim.scene import RaycastScene, build_mesh
from sensors.sim.sensing import (
    RobotBody,
    SimulatedScanner,
    robot_cylinders,
    scan_stream,
    telegram_times,
)
from sensors.sim.world import world_from_mapping

LIMITS = ScanLimits.for_variant(100, 1.0, unit_mm=True, baud_rate=38400)
K = LIMITS.turns_per_telegram  # 6 at 38 400 Bd (§8)
RANGES = np.linspace(1.0, 6.0, 101)
#: A 9 m × 6 m room with a 3 m ceiling.
ROOM = {"name": "room", "rooms": [{"name": "r", "footprint": [[0, 0], [9, 0], [9, 6], [0, 6]],
                                   "ceiling_m": 3.0}]}  # fmt: skip


def stamp_of(turn: int, size: int = 214) -> float:
    """Host receive time of a telegram measured at ``turn``, as the simulator stamps it."""
    return (turn + 1) * TURN_S + size * 10.0 / 38400 + 0.002


def frame_at(
    k: int, *, turn: int | None = None, telegram: int | None = None, **kw: object
) -> bytes:
    """The k-th telegram of a stream: scan index = its turn, telegram index = k (mod 256)."""
    turn = 1000 + K * k if turn is None else turn
    return encode_scan(RANGES, scan_index=turn & 0xFF,
                       telegram_index=(k if telegram is None else telegram) & 0xFF, **kw)  # type: ignore[arg-type]  # fmt: skip


def decoded(data: bytes, stamp_s: float | None, measuring_mode: int = 1) -> Scan:
    """The telegram as the stream parser finds it (so its checksum is valid), decoded."""
    parser = StreamParser()
    events = [e for e in parser.feed(data, stamp_s) + parser.close() if isinstance(e, Telegram)]
    assert len(events) == 1
    assert parser.stats.checksum_failures == 0
    return decode_scan(events[0], measuring_mode)


def good(k: int) -> Scan:
    return decoded(frame_at(k), stamp_of(1000 + K * k))


def verdicts(scans: list[Scan], limits: ScanLimits = LIMITS) -> list[str | None]:
    check = ScanCheck(limits)
    found = [check.check(s) for s in scans]
    assert check.accepted == found.count(None)
    assert check.rejected_total == len(found) - found.count(None)
    return [None if r is None else r.value for r in found]


def words_frame(words: np.ndarray, count_word: int, tail: bytes = b"", status: int = 0x10) -> bytes:
    payload = struct.pack("<H", count_word) + np.asarray(words, "<u2").tobytes() + tail
    return reply_frame(0xB0, payload, status)


# --------------------------------------------------------------------------------------------
# Rules without the sequence


def test_a_clean_simulated_stream_has_no_rejections() -> None:
    scans = [decoded(data, stamp) for stamp, data in simulated_stream(40.0)]
    assert len(scans) == 500
    assert sum(np.isnan(s.ranges_m).all() for s in scans) > 150  # mirror folded away
    assert sum((s.flags > 0).any() for s in scans) > 5  # the other robot's beacon
    assert verdicts(scans) == [None] * len(scans)


def test_a_scan_of_another_variant_is_rejected_and_its_neighbours_kept() -> None:
    other = encode_scan(np.full(181, 2.0), scan_index=(1000 + K) & 0xFF, telegram_index=1)
    scans = [good(0), decoded(other, stamp_of(1000 + K, 374)), good(2)]
    assert verdicts(scans) == [None, "count", None]


@pytest.mark.parametrize("extra_bits", [0x0400, 0x2000, 0x2800])
def test_count_word_bits_no_complete_scan_sets_are_rejected(extra_bits: int) -> None:
    """Bit 10 is undocumented; bit 13 (partial) and 11–12 (its offset) belong to interlacing."""
    words = np.round(RANGES * 1000).astype(np.uint16)
    tail = bytes(((1000 + K) & 0xFF, 1))
    crafted = decoded(words_frame(words, 0x4065 | extra_bits, tail), stamp_of(1000 + K))
    assert verdicts([good(0), crafted, good(2)]) == [None, "count", None]


def test_index_bytes_must_be_as_configured_or_as_the_stream_began() -> None:
    without = decoded(encode_scan(RANGES), stamp_of(1000 + K, 212))
    assert verdicts([good(0), without, good(2)]) == [None, "length", None]
    assert verdicts([without, good(2)]) == [None, "length"]  # the stream began without them
    fixed = ScanLimits(101, True, 38400, realtime_indices=False)
    assert verdicts([without, good(2)], fixed) == [None, "length"]
    assert verdicts([good(0), without], fixed) == ["length", None]


def test_a_scan_in_the_other_unit_is_rejected() -> None:
    cm = decoded(frame_at(1, unit_mm=False), stamp_of(1000 + K))
    assert cm.unit_m == pytest.approx(0.01)
    assert verdicts([good(0), cm, good(2)]) == [None, "unit", None]
    in_cm = ScanLimits(101, False, 38400)
    assert verdicts([cm], in_cm) == [None]


@pytest.mark.parametrize(
    ("mode", "unit_mm", "raw", "expected"),
    [
        (1, True, 8080, None),  # 8 m + 1 %
        (1, True, 8081, "range"),
        (1, True, 8182, "range"),  # the largest value below the codes
        (1, True, 0x1FFF - 3, "range"),  # an undocumented code
        (1, True, 0x1FFF - 7, "range"),
        (1, True, 0x1FFF - 8, None),  # OUT_OF_RANGE
        (1, True, 0x1FFF - 5, None),  # CHANNEL_ERROR
        (1, True, 0xFFFF, None),  # no return, reflector value 7
        (3, True, 16160, None),
        (3, True, 16161, "range"),
        (5, True, 32320, None),
        (5, True, 32321, "range"),
        (1, False, 8080, None),  # 80.8 m in cm
        (3, False, 8081, "range"),  # every mode stops at 80 m in cm
        (15, True, 0x7FFF, None),
        (15, True, 0x8000 | 1000, "flags"),  # mode 15 sets no flag bit
    ],
)
def test_ranges_and_flag_bits_the_mode_cannot_send_are_rejected(
    mode: int, unit_mm: bool, raw: int, expected: str | None
) -> None:
    words = np.full(101, 1500, dtype=np.uint16)
    words[40] = raw
    unit = 0x4000 if unit_mm else 0
    data = words_frame(words, 101 | unit, bytes(((1000 + K) & 0xFF, 1)))
    limits = ScanLimits(101, unit_mm, 38400)
    first = decoded(words_frame(np.full(101, 1500), 101 | unit, bytes((1000 & 0xFF, 0))),
                    stamp_of(1000), mode)  # fmt: skip
    assert verdicts([first, decoded(data, stamp_of(1000 + K), mode)], limits) == [None, expected]


def test_an_error_level_above_4_is_rejected() -> None:
    assert verdicts([good(0), decoded(frame_at(1, status=0x14), stamp_of(1000 + K))]) == [None] * 2
    bad = decoded(frame_at(1, status=0x15), stamp_of(1000 + K))
    assert verdicts([good(0), bad, good(2)]) == [None, "status", None]


# --------------------------------------------------------------------------------------------
# The sequence of real-time indices


def with_indices(k: int, scan_index: int, telegram_index: int) -> Scan:
    data = frame_at(k, turn=scan_index, telegram=telegram_index)
    return decoded(data, stamp_of(1000 + K * k))


@pytest.mark.parametrize(
    ("scan_index", "telegram_index"),
    [
        ((1000 + 2 * K - 6) & 0xFF, 2),  # the scan index went backwards
        ((1000 + 2 * K + 100) & 0xFF, 2),  # far ahead of the elapsed time
        ((1000 + 2 * K + 2) & 0xFF, 2),  # 2 turns (27 ms) ahead
        ((1000 + 2 * K) & 0xFF, 7),  # 5 telegrams in 1 interval
        ((1000 + 2 * K) & 0xFF, 1),  # the telegram index repeated
        ((1000 + 2 * K) & 0xFF, 255),  # the telegram index went backwards
        ((1000 + K) & 0xFF, 1),  # the whole telegram repeated
    ],
)
def test_an_inconsistent_index_rejects_that_telegram_only(
    scan_index: int, telegram_index: int
) -> None:
    scans = [good(0), good(1), with_indices(2, scan_index, telegram_index), good(3), good(4)]
    assert verdicts(scans) == [None, None, "sequence", None, None]


def test_a_telegram_counter_starting_again_from_0_is_kept() -> None:
    """The simulator's counter restarts with each chunk of scans; a scan index that agrees with
    the host clock keeps the scan, and the ones after it follow the new count."""
    scans = [good(k) for k in range(3)]
    scans += [decoded(frame_at(k, telegram=k - 3), stamp_of(1000 + K * k)) for k in range(3, 6)]
    assert verdicts(scans) == [None] * 6
    early = decoded(frame_at(3, turn=1000 + K * 3 + 3, telegram=0), stamp_of(1000 + K * 3))
    assert verdicts([*scans[:3], early]) == [None, None, None, "sequence"]


def test_lost_telegrams_and_long_gaps_are_kept() -> None:
    kept = [0, 1, 4, 5, 60, 61, 62, 400, 401]  # gaps of 2, 54 (324 turns) and 337 telegrams
    assert verdicts([good(k) for k in kept]) == [None] * len(kept)


def test_late_telegrams_of_a_host_stall_are_kept() -> None:
    """Telegrams buffered during a 0.6 s stall arrive together, with one stamp."""
    stall = stamp_of(1000 + K * 9) + 0.01  # telegram 3 arrives 0.49 s late
    scans = [good(k) for k in range(3)]
    scans += [decoded(frame_at(k), stall) for k in range(3, 10)]
    scans += [good(k) for k in range(10, 14)]
    assert verdicts(scans) == [None] * len(scans)


def test_a_restarted_counter_costs_one_scan() -> None:
    """After a reset the indices start afresh: two scans that agree begin a new sequence."""
    restarted = [decoded(frame_at(k, turn=17 + K * k, telegram=k - 5), stamp_of(1000 + K * k))
                 for k in range(5, 9)]  # fmt: skip
    assert (
        verdicts([good(k) for k in range(5)] + restarted) == [None] * 5 + ["sequence"] + [None] * 3
    )


def test_without_host_stamps_the_indices_alone_are_checked() -> None:
    scans = [decoded(frame_at(k), None) for k in range(3)]
    scans.append(decoded(frame_at(3, turn=1000 + K * 3 + 3), None))  # 9 turns in 1 telegram
    scans.append(decoded(frame_at(4, turn=1000 + K * 4 + 1), None))  # 13 in 2: a scan lost
    scans.append(decoded(frame_at(6, turn=1000 + K * 6 + 1), None))  # 12 in 2: a telegram lost
    scans.append(decoded(frame_at(7), None))  # 5 turns in 1 telegram
    assert verdicts(scans) == [None, None, None, "sequence", None, None, "sequence"]


def test_limits_refuse_what_the_lms_200_does_not_have() -> None:
    assert ScanLimits.for_variant(180, 0.5, unit_mm=True, baud_rate=500000).count == 361
    assert ScanLimits.for_variant(180, 0.5, unit_mm=True, baud_rate=500000).turns_per_telegram == 2
    with pytest.raises(ProtocolError, match=r"no 180°/0\.25° variant"):
        ScanLimits.for_variant(180, 0.25, unit_mm=True, baud_rate=38400)
    with pytest.raises(ProtocolError, match="got 100"):
        ScanLimits(100, True, 38400)
    with pytest.raises(ProtocolError, match=r"baud rate must be one of .* got 57600"):
        ScanLimits(101, True, 57600)
    with pytest.raises(ProtocolError, match="early_s must be"):
        ScanLimits(101, True, 38400, early_s=0.02)
    assert Implausible.SEQUENCE == "sequence"


# --------------------------------------------------------------------------------------------
# What the rules catch of the corruptions that pass the checksum


def simulated_stream(seconds: float) -> list[tuple[float, bytes]]:
    """The capture chunks of a scanner at rest in a room, another robot's beacon in view."""
    scene = RaycastScene(build_mesh(world_from_mapping(ROOM)))
    geometry = MirrorGeometry(axis_offset_m=0.1, gear_ratio=80.0, nominal_motor_period_s=0.5)
    scanner = SimulatedScanner(geometry, motor_period_s=0.5, edge_on_turn=5)
    times = telegram_times(0.0, seconds, 38400, 101, 1.0)
    others = robot_cylinders(RobotBody(), np.array([(6.0, 4.0, 2.0)]))[0]
    simulated = scanner.scan(
        scene, scanner_pose_matrix(2.0, 3.0, 0.3, 0.1, 0.45), times, np.random.default_rng(0),
        cylinders=np.broadcast_to(others, (len(times), *others.shape)),
    )  # fmt: skip
    return scan_stream(simulated)


def passing_double_flips(size: int) -> np.ndarray:
    """(P, 2) bit numbers of every double-bit flip of a ``size``-byte frame that leaves the
    checksum valid, except those touching LEN.

    The checksum is linear over GF(2) with a zero start, so two flips pass together exactly
    when their syndromes are equal (a flip inside the checksum field is its own syndrome).
    """
    syndromes = np.empty(size * 8, dtype=np.int64)
    for bit in range(size * 8):
        byte = bit // 8
        if byte < size - 2:
            buf = np.zeros(size, dtype=np.uint8)
            buf[byte] = 1 << (bit % 8)
            syndromes[bit] = checksum_kernel(buf, 0, size - 2)
        else:
            syndromes[bit] = (1 << (bit % 8)) << (8 * (byte - (size - 2)))
    pairs = [(a, b) for a in range(size * 8) for b in np.flatnonzero(syndromes[a + 1 :] == syndromes[a]) + a + 1]  # fmt: skip
    return np.array([p for p in pairs if not any(16 <= q < 32 for q in p)])


def test_double_bit_flips_that_pass_the_checksum() -> None:
    """Double-bit flips of simulated telegrams that keep the checksum valid: what gets through.

    214-byte telegrams (100°/1°, real-time indices, 38 400 Bd) of a simulated scanner at rest in
    a 9 × 6 m room, half of its scans folded away (all no return). Of a telegram's 1,464,616
    double flips, 5,752 leave the checksum valid without touching LEN (none of the 27,376 that
    touch LEN yields a telegram: tried once through the stream parser). 500 of them on each of
    41 telegrams, each checked after the good scans before it — measured with seed 0:

    * 20,500 trials: 199 are no scan any more (code not B0, or ADDR bit 7 cleared), 176 are
      undecodable, 20,125 decode to an altered scan;
    * caught: 4,046 of the 20,125 (20.1 %): range 3,781, sequence 201, count 51, unit 13; 206
      of the 207 with altered real-time indices;
    * through: 16,079 (79.9 %): 5,114 with a no-return turned into a range, 5,715 with a range
      moved by more than 0.1 m, 3,700 moved less or only flags changed, 1,524 with a range
      turned into a code; 25 with only the status byte altered, 1 with its telegram index
      turned into 0 (taken for a restarted counter; its values are intact);
    * the good telegram after each corrupted one is kept every time.
    """
    chunks = simulated_stream(40.0)
    size = len(chunks[0][1])
    flips = passing_double_flips(size)
    assert size == 214
    assert len(flips) == 5752
    scans = [decoded(data, stamp) for stamp, data in chunks]
    rng = np.random.default_rng(0)
    outcome: Counter[str] = Counter()
    reasons: Counter[str] = Counter()
    before = ScanCheck(LIMITS)
    next_lost = 0
    for k, scan in enumerate(scans[:-1]):
        if k >= 10 and k % 12 == 0:
            stamp, data = chunks[k]
            original = np.frombuffer(data, dtype=np.uint8)
            for a, b in flips[rng.choice(len(flips), 500, replace=False)]:
                corrupt = original.copy()
                corrupt[a // 8] ^= 1 << (a % 8)
                corrupt[b // 8] ^= 1 << (b % 8)
                parser = StreamParser()
                found = [
                    e for e in parser.feed(corrupt.tobytes(), stamp) if isinstance(e, Telegram)
                ]
                assert checksum(corrupt[:-2].tobytes()) == int(corrupt[-2]) | int(corrupt[-1]) << 8
                if not found or found[0].code != 0xB0:
                    outcome["not a scan"] += 1
                    continue
                try:
                    altered = decode_scan(found[0])
                except ProtocolError:
                    outcome["undecodable"] += 1
                    continue
                measured = (
                    not np.array_equal(altered.raw, scan.raw) or altered.unit_m != scan.unit_m
                )
                indices = (altered.scan_index, altered.telegram_index) != (
                    scan.scan_index, scan.telegram_index)  # fmt: skip
                kind = "indices" if indices else "measured" if measured else "other"
                trial = before.copy()
                reason = trial.check(altered)
                if reason is None:
                    outcome[f"{kind} through"] += 1
                else:
                    outcome[f"{kind} caught"] += 1
                    reasons[reason.value] += 1
                next_lost += trial.check(scans[k + 1]) is not None
        assert before.check(scan) is None
    assert next_lost == 0
    caught = sum(n for key, n in outcome.items() if key.endswith("caught"))
    altered_total = caught + sum(n for key, n in outcome.items() if key.endswith("through"))
    assert altered_total > 19000
    assert caught / altered_total > 0.18
    assert outcome["indices caught"] > 150
    assert outcome["indices through"] <= 2
    assert reasons["range"] > 3000
    assert reasons["sequence"] > 150


# --------------------------------------------------------------------------------------------
# Where the rules are applied: `coopmap lms decode`


def test_lms_decode_marks_and_counts_implausible_scans(tmp_path: Path) -> None:
    path = tmp_path / "run.cap"
    with CaptureWriter(path, {"baud_rate": 38400}) as writer:
        for k in range(4):
            data = frame_at(k, turn=1000 + K * k + (100 if k == 2 else 0))
            writer.write(stamp_of(1000 + K * k), data)
    records, summary = decode_stream(CaptureReader(path), 1, "any", LIMITS)
    kinds = [(r["kind"], r.get("reason")) for r in records]
    assert kinds == [("scan", None), ("scan", None), ("implausible", "sequence"), ("scan", None)]
    assert (summary.scans, summary.implausible, summary.implausible_reasons) == (
        3, 1, {"sequence": 1})  # fmt: skip
    unchecked, _ = decode_stream(CaptureReader(path))
    assert [r["kind"] for r in unchecked] == ["scan"] * 4
    text = CliRunner().invoke(app, ["lms", "decode", str(path)])
    assert text.exit_code == 0
    assert "implausible  B0  sequence" in text.stdout
    assert "0 undecodable, 1 implausible (sequence 1), 0 bytes skipped" in text.stdout
    as_json = CliRunner().invoke(app, ["lms", "decode", str(path), "--json"])
    summary_line = json.loads(as_json.stdout.splitlines()[-1])
    assert (summary_line["implausible"], summary_line["implausible_reasons"]) == (
        1, {"sequence": 1})  # fmt: skip
