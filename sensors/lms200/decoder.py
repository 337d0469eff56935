"""Measured values of one LMS byte stream, decoded a chunk or a whole capture at a time.

:class:`ScanDecoder` is what a host needs of a sensor's stream: it frames the bytes as
:class:`~sensors.lms200.protocol.stream.StreamParser` does (the same kernel, chunk by chunk),
decodes every ``B0`` telegram (:func:`~sensors.lms200.protocol.scan.decode_scans`) and, given
the configured sensor's limits, drops the implausible ones
(:meth:`~sensors.lms200.protocol.plausibility.ScanCheck.check_batch`). Nothing on the way is
a Python loop per telegram: fed a whole capture (:meth:`ScanDecoder.feed_stream`, one call)
or a chunk at a time (:meth:`ScanDecoder.feed`), it runs the same kernels and gives the same
scans and counts. Only building the :class:`~sensors.lms200.protocol.scan.Scan` objects is
per scan; their arrays are views of the batch's.

:mod:`sensors.lms200.reference` keeps the per-telegram path this replaced, for the tests and
``coopmap bench decode`` to compare against.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sensors.lms200.capture import CaptureStream
from sensors.lms200.protocol.plausibility import ScanCheck, ScanLimits
from sensors.lms200.protocol.scan import Scan, decode_scans
from sensors.lms200.protocol.stream import scan_chunks
from sensors.lms200.protocol.telegram import DISTANCE_MASK, MAX_LEN, ProtocolError

__all__ = ["DecoderStats", "ScanDecoder"]

_FROM_SENSOR = 0  # StreamParser's direction code for replies
_MEASURED_VALUES = 0xB0


@dataclass
class DecoderStats:
    """What a :class:`ScanDecoder` has seen so far."""

    bytes_in: int = 0
    telegrams: int = 0  # checksum-valid frames of any reply
    decoded: int = 0  # measured-value telegrams decoded (accepted or not)
    undecodable: int = 0  # measured-value telegrams that are malformed
    checksum_failures: int = 0
    bytes_skipped: int = 0
    acks: int = 0
    naks: int = 0


class ScanDecoder:
    """One sensor's stream → its plausible scans, in order, each with its receive stamp.

    A scan without a receive stamp (a plain dump) is decoded and counted but not returned:
    nothing could place it in time. With ``limits``, ``check`` holds the rejections by reason.
    """

    def __init__(self, measuring_mode: int = 1, limits: ScanLimits | None = None) -> None:
        if measuring_mode not in DISTANCE_MASK:
            raise ProtocolError(f"unknown measuring mode {measuring_mode}")
        self.measuring_mode = measuring_mode
        self.check = ScanCheck(limits) if limits is not None else None
        self.stats = DecoderStats()
        self._held = np.zeros(0, np.uint8)
        self._last_stamp: float | None = None

    @property
    def pending(self) -> int:
        """Bytes held while waiting for the rest of a frame."""
        return len(self._held)

    def feed(self, chunk: bytes, stamp_s: float | None = None) -> list[Scan]:
        """Decode one received chunk; returns the plausible scans it completed."""
        self._last_stamp = stamp_s
        return self._decode(
            np.frombuffer(chunk, dtype=np.uint8),
            np.array([len(chunk)], np.int64),
            np.array([np.nan if stamp_s is None else stamp_s]),
            np.array([stamp_s is not None]),
            final=False,
        )

    def feed_chunks(self, chunks: Sequence[tuple[float | None, bytes]]) -> list[Scan]:
        """Decode received chunks (receive stamp, bytes) in one call: the same as feeding them
        one by one."""
        if not chunks:
            return []
        stamps = np.array([np.nan if t is None else t for t, _ in chunks], dtype=np.float64)
        ends = np.cumsum([len(data) for _, data in chunks], dtype=np.int64)
        data = np.frombuffer(b"".join(data for _, data in chunks), dtype=np.uint8)
        self._last_stamp = chunks[-1][0]
        return self._decode(data, ends, stamps, ~np.isnan(stamps), final=False)

    def feed_stream(self, stream: CaptureStream) -> list[Scan]:
        """Decode a whole capture's stream: the same as feeding its records one by one."""
        if len(stream.ends) == 0:
            return []
        stamped = ~np.isnan(stream.stamps_s)
        self._last_stamp = float(stream.stamps_s[-1]) if stamped[-1] else None
        return self._decode(stream.data, stream.ends, stream.stamps_s, stamped, final=False)

    def close(self) -> list[Scan]:
        """End of stream: parse what is held, as :meth:`StreamParser.close` does."""
        stamp = self._last_stamp
        return self._decode(
            np.zeros(0, np.uint8),
            np.zeros(1, np.int64),
            np.array([np.nan if stamp is None else stamp]),
            np.array([stamp is not None]),
            final=True,
        )

    def _decode(
        self, data: np.ndarray, ends: np.ndarray, stamps_s: np.ndarray, stamped: np.ndarray,
        *, final: bool,
    ) -> list[Scan]:  # fmt: skip
        held = len(self._held)
        buf = np.concatenate([self._held, data]) if held else data
        frames, counts = scan_chunks(buf, ends + held, _FROM_SENSOR, MAX_LEN, final)
        consumed, skipped, failures, acks, naks = counts.tolist()
        stats = self.stats
        stats.bytes_in += len(data)
        stats.telegrams += len(frames)
        stats.bytes_skipped += skipped
        stats.checksum_failures += failures
        stats.acks += acks
        stats.naks += naks
        self._held = buf[consumed:].copy()
        scans = frames[buf[frames[:, 0] + 4] == _MEASURED_VALUES]
        where = np.column_stack([scans[:, 0] + 5, scans[:, 1] - 8])  # data: after the code
        status = buf[scans[:, 0] + scans[:, 1] - 3]  # before the status byte
        batch = decode_scans(buf, where, status, self.measuring_mode)
        well_formed = batch.errors == 0
        stats.decoded += int(np.count_nonzero(well_formed))
        stats.undecodable += int(len(well_formed) - np.count_nonzero(well_formed))
        chunk = scans[:, 2]
        rows = np.flatnonzero(well_formed & stamped[chunk])
        stamps = stamps_s[chunk[rows]]
        if self.check is not None:
            keep = self.check.check_batch(batch, rows, stamps, np.ones(len(rows), bool))
            rows, stamps = rows[keep], stamps[keep]
        return batch.scans(rows, stamps.tolist())
