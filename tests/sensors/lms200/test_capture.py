"""Capture files and their decoding, including the `coopmap lms decode` command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from estimation.app.cli.main import app
from sensors.lms200.capture import CaptureError, CaptureReader, CaptureWriter, decode_stream
from sensors.lms200.protocol.commands import cmd_stop
from sensors.lms200.protocol.replies import encode_mode_reply
from sensors.lms200.protocol.scan import SpecialCode, encode_scan
from sensors.lms200.protocol.telegram import reply_frame

SCAN = encode_scan(np.linspace(0.5, 7.5, 101), flags=np.arange(101) % 8, scan_index=6)
TYPE = reply_frame(0xBA, b"LMS200;301063;V02.10 ")


def write_capture(path: Path) -> Path:
    with CaptureWriter(path, {"port": "test", "baud_rate": 38400}) as writer:
        writer.write(0.0, b"\x06" + encode_mode_reply(0))
        writer.write(0.08, SCAN[:100])
        writer.write(0.09, SCAN[100:])
        writer.write(0.2, b"junk" + TYPE)
    return path


def test_capture_round_trip_keeps_bytes_and_stamps(tmp_path: Path) -> None:
    path = write_capture(tmp_path / "run.cap")
    reader = CaptureReader(path)
    assert reader.is_capture
    assert reader.header is not None
    assert reader.header["baud_rate"] == 38400
    chunks = list(reader.chunks())
    assert [s for s, _ in chunks] == [0.0, 0.08, 0.09, 0.2]
    assert b"".join(c for _, c in chunks) == b"\x06" + encode_mode_reply(0) + SCAN + b"junk" + TYPE
    assert not (tmp_path / "run.cap.partial").exists()


def test_decode_stream_counts_everything(tmp_path: Path) -> None:
    records, summary = decode_stream(CaptureReader(write_capture(tmp_path / "run.cap")))
    records = list(records)
    assert [r["kind"] for r in records] == ["ack", "reply", "scan", "reply"]
    scan = records[2]
    assert scan["code"] == 0xB0
    assert scan["crc_ok"] is True
    assert scan["stamp_s"] == 0.09  # the chunk that completed the frame
    assert scan["unit"] == "mm"
    assert scan["scan_index"] == 6
    assert scan["ranges_m"][:2] == [0.5, 0.57]
    assert scan["flags"][:9] == [0, 1, 2, 3, 4, 5, 6, 7, 0]
    assert records[3]["text"] == "LMS200;301063;V02.10 "
    assert (summary.telegrams, summary.scans, summary.acks, summary.bytes_skipped) == (3, 1, 1, 4)


def test_plain_dump_with_invalid_values_and_bad_checksum(tmp_path: Path) -> None:
    ranges = np.full(101, 2.0)
    ranges[5] = np.nan
    bad = bytearray(TYPE)
    bad[10] ^= 0x01
    dump = tmp_path / "dump.bin"
    dump.write_bytes(cmd_stop() + encode_scan(ranges) + bytes(bad) + SCAN[:30])
    records, summary = decode_stream(CaptureReader(dump))
    records = list(records)
    assert [r["kind"] for r in records] == ["command", "scan", "bad_checksum"]
    assert records[1]["ranges_m"][5] is None
    assert records[1]["codes"][5] == SpecialCode.NO_RETURN
    assert records[2]["crc_ok"] is False
    assert summary.checksum_failures == 1
    assert summary.bytes_skipped == len(bad) + 30


def test_truncated_capture_keeps_complete_records(tmp_path: Path) -> None:
    path = write_capture(tmp_path / "run.cap")
    cut = tmp_path / "cut.cap"
    cut.write_bytes(path.read_bytes()[:-10])
    reader = CaptureReader(cut)
    records, summary = decode_stream(reader)
    kinds = [r["kind"] for r in records]
    assert kinds == ["ack", "reply", "scan"]
    assert summary.truncated_bytes == 12 + len(b"junk" + TYPE) - 10


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"COOPMAP-LMSCAP 1\n{not json\n", r"capture header is not JSON"),
        (b"COOPMAP-LMSCAP 1\n[1, 2]\n", r"capture header is not a JSON object"),
        (b'COOPMAP-LMSCAP 1\n{"a": 1}', r"capture header line is truncated"),
    ],
)
def test_corrupt_headers_are_clear_errors(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bad.cap"
    path.write_bytes(content)
    with pytest.raises(CaptureError, match=message):
        CaptureReader(path)


def numbered_capture(path: Path, records: int = 40) -> list[tuple[float, bytes]]:
    written = [(0.01 * k, bytes([k]) * (5 + k % 7)) for k in range(records)]
    with CaptureWriter(path) as writer:
        for stamp, chunk in written:
            writer.write(stamp, chunk)
    return written


def test_a_corrupt_record_header_is_skipped_and_reading_goes_on(tmp_path: Path) -> None:
    path = tmp_path / "bad.cap"
    written = numbered_capture(path)
    data = bytearray(path.read_bytes())
    header = CaptureReader(path)._offset
    # Record 10's header: its size becomes 4 GiB (impossible), its stamp NaN.
    at = header + sum(12 + len(c) for _, c in written[:10])
    data[at : at + 12] = b"\xff" * 12
    path.write_bytes(bytes(data))
    reader = CaptureReader(path)
    chunks = list(reader.chunks())
    assert chunks == written[:10] + written[11:]  # only the damaged record is lost
    assert reader.resyncs == 1
    assert reader.corrupt_bytes == 12 + len(written[10][1])
    assert reader.truncated_bytes == 0


def test_zeroed_and_random_stretches_lose_only_the_records_they_hit(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    path = tmp_path / "bad.cap"
    written = numbered_capture(path, 200)
    clean = path.read_bytes()
    header = CaptureReader(path)._offset
    starts = np.cumsum([header] + [12 + len(c) for _, c in written])
    for fill in (bytes(300), rng.bytes(300)):
        data = bytearray(clean)
        at = int(starts[50]) + 7
        data[at : at + 300] = fill
        path.write_bytes(bytes(data))
        reader = CaptureReader(path)
        chunks = list(reader.chunks())
        hit = {k for k in range(200) if starts[k] < at + 300 and starts[k + 1] > at}
        assert chunks == [w for k, w in enumerate(written) if k not in hit]
        assert reader.resyncs >= 1
        assert reader.corrupt_bytes == int(starts[max(hit) + 1] - starts[min(hit)])


def test_a_capture_that_is_garbage_after_its_header_yields_nothing(tmp_path: Path) -> None:
    path = tmp_path / "bad.cap"
    path.write_bytes(b"COOPMAP-LMSCAP 1\n{}\n" + b"\x00" * 8 + b"\xff\xff\xff\xff" + b"data")
    reader = CaptureReader(path)
    assert list(reader.chunks()) == []
    assert reader.corrupt_bytes == 16
    assert reader.resyncs == 1


def test_a_pipe_is_refused_before_it_is_opened(tmp_path: Path) -> None:
    import os

    fifo = tmp_path / "lms.cap"
    os.mkfifo(fifo)
    with pytest.raises(CaptureError, match="not a regular file"):
        CaptureReader(fifo)
    with pytest.raises(CaptureError, match="is a directory"):
        CaptureReader(tmp_path)


def test_writer_never_clobbers_and_missing_files_are_errors(tmp_path: Path) -> None:
    path = write_capture(tmp_path / "run.cap")
    before = path.read_bytes()
    with pytest.raises(CaptureError, match="already exists"):
        CaptureWriter(path)
    assert path.read_bytes() == before
    with pytest.raises(CaptureError, match="no such file"):
        CaptureReader(tmp_path / "absent.cap")
    with pytest.raises(CaptureError, match="is a directory"):
        CaptureReader(tmp_path)
    writer = CaptureWriter(tmp_path / "x.cap")
    writer.close()
    with pytest.raises(CaptureError, match="already closed"):
        writer.write(0.0, b"x")


def test_interrupted_recording_leaves_a_readable_partial(tmp_path: Path) -> None:
    writer = CaptureWriter(tmp_path / "live.cap")
    writer.write(0.0, SCAN)
    writer.flush()  # the process dies here: the .partial holds every flushed record
    records, _ = decode_stream(CaptureReader(writer.partial))
    assert [r["kind"] for r in records] == ["scan"]
    writer.close()


def test_a_new_recording_never_truncates_a_crashed_ones_partial(tmp_path: Path) -> None:
    crashed = CaptureWriter(tmp_path / "live.cap")
    for k in range(79):
        crashed.write(float(k), SCAN)
    crashed.flush()  # the process dies here, leaving live.cap.partial
    size = crashed.partial.stat().st_size
    with pytest.raises(CaptureError, match=r"live\.cap\.partial: a recording that was cut short"):
        CaptureWriter(tmp_path / "live.cap")
    assert crashed.partial.stat().st_size == size
    records, _ = decode_stream(CaptureReader(crashed.partial))
    assert sum(r["kind"] == "scan" for r in records) == 79


def test_lms_decode_cli_json_and_text(tmp_path: Path) -> None:
    path = write_capture(tmp_path / "run.cap")
    result = CliRunner().invoke(app, ["lms", "decode", str(path), "--json"])
    assert result.exit_code == 0
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    assert [line["kind"] for line in lines] == ["ack", "reply", "scan", "reply", "summary"]
    assert lines[-1]["telegrams"] == 3
    assert lines[-1]["scans"] == 1
    assert lines[-1]["checksum_failures"] == 0
    assert lines[-1]["bytes_skipped"] == 4
    text = CliRunner().invoke(app, ["lms", "decode", str(path)])
    assert text.exit_code == 0
    assert "101 values, 101 valid, 88 flagged, mm, scan index 6" in text.stdout
    assert "3 telegrams (1 scans, 2 replies, 0 commands)" in text.stdout


def test_lms_decode_cli_errors(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["lms", "decode", str(tmp_path / "absent.cap")])
    assert result.exit_code == 2
    assert result.stderr.strip() == f"coopmap: error: {tmp_path / 'absent.cap'}: no such file"
    dump = tmp_path / "d.bin"
    dump.write_bytes(b"x")
    result = CliRunner().invoke(app, ["lms", "decode", str(dump), "--direction", "up"])
    assert result.exit_code == 2
    assert "direction must be one of" in result.stderr


def test_discarded_recording_leaves_nothing(tmp_path: Path) -> None:
    writer = CaptureWriter(tmp_path / "x.cap")
    writer.discard()
    assert list(tmp_path.iterdir()) == []
