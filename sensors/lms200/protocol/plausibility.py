"""Plausibility of measured-value telegrams that passed the checksum (§6, §8, §13); no I/O.

SICK's checksum (§3) is weak by design, so a corrupted ``B0`` telegram now and then passes it.
:func:`implausibility` rejects a decoded scan whose bits the configured sensor cannot send;
:class:`ScanCheck`, fed the scans of one stream in order, adds the real-time indices' sequence.
Each rejection has a reason (:class:`Implausible`):

* ``count`` — the count word is not the configured variant's: another value count, a partial
  scan, or the undocumented bit 10 set (§6.3);
* ``length`` — real-time index bytes present where the configuration has none, or missing
  (§6.1); without a configured choice, the stream's first plausible scan decides;
* ``unit`` — the unit bits are not the configured unit (§6.3);
* ``range`` — a distance beyond the measuring mode's maximum that is not a documented special
  code (§6.2, §6.4);
* ``flags`` — a bit the measuring mode never sets (mode 15 has none above its 15 distance bits);
* ``status`` — an error level above 4 in the status byte (§7);
* ``sequence`` — scan index and telegram index do not advance as the telegram interval and the
  elapsed host time allow (§8, §13).

Sections (§n) cite docs/lms200-protocol.md.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from sensors.lms200.protocol.scan import VARIANT_BY_COUNT, Scan, scan_interval_s
from sensors.lms200.protocol.telegram import (
    BAUD_RATES,
    DISTANCE_MASK,
    FLAG_SHIFT,
    TURN_S,
    ProtocolError,
)

__all__ = [
    "MODE_MAX_RANGE_M",
    "Implausible",
    "ScanCheck",
    "ScanLimits",
    "implausibility",
]


class Implausible(enum.StrEnum):
    """Why a checksum-valid scan was rejected."""

    COUNT = "count"
    LENGTH = "length"
    UNIT = "unit"
    RANGE = "range"
    FLAGS = "flags"
    STATUS = "status"
    SEQUENCE = "sequence"


#: Longest range of each measuring mode in the mm unit (§6.2); in cm every mode reaches 80 m.
MODE_MAX_RANGE_M = {0: 8.0, 1: 8.0, 2: 8.0, 3: 16.0, 4: 16.0, 5: 32.0, 6: 32.0, 15: 32.0}
CM_MAX_RANGE_M = 80.0
#: A target at the nominal maximum may read this much further (range noise and offset).
RANGE_MARGIN = 1.01
# Gaps below the mask (mask − raw) that are documented special codes (§6.4).
_DOCUMENTED_GAPS = (0, 1, 2, 4, 5, 8)
_COUNT_BITS = 0x03FF
_UNIT_SHIFT = 14


@dataclass(frozen=True)
class ScanLimits:
    """What the configured sensor sends: the variant's value count, the unit, the line rate.

    ``realtime_indices`` None: whichever the stream's first plausible scan has. ``early_s`` is
    how far a scan's turn count may run ahead of the host clock (timer resolution and clock
    drift: a telegram never arrives before it was measured); ``late_s`` how much later than the
    earliest seen a telegram may still arrive (host stalls, USB buffering).
    """

    count: int
    unit_mm: bool
    baud_rate: int
    realtime_indices: bool | None = None
    early_s: float = 0.005
    late_s: float = 1.0

    def __post_init__(self) -> None:
        if self.count not in VARIANT_BY_COUNT:
            raise ProtocolError(f"a variant has 101, 201, 401, 181 or 361 values, got {self.count}")
        if self.baud_rate not in BAUD_RATES:
            raise ProtocolError(f"baud rate must be one of {BAUD_RATES}, got {self.baud_rate}")
        if not (0 <= self.early_s < TURN_S and 0 < self.late_s < 200 * TURN_S):
            raise ProtocolError(
                f"early_s must be in [0, {TURN_S}) and late_s in (0, {200 * TURN_S:.2f}) s, "
                f"got {self.early_s} and {self.late_s}"
            )

    @classmethod
    def for_variant(
        cls,
        field_of_view_deg: int,
        angular_resolution_deg: float,
        *,
        unit_mm: bool,
        baud_rate: int,
        realtime_indices: bool | None = None,
    ) -> ScanLimits:
        """The limits of a variant (§5.3): 100° at 1, 0.5, 0.25° or 180° at 1, 0.5°."""
        counts = {variant: count for count, variant in VARIANT_BY_COUNT.items()}
        variant = (field_of_view_deg, float(angular_resolution_deg))
        if variant not in counts:
            raise ProtocolError(
                f"the LMS 200 has no {field_of_view_deg}°/{angular_resolution_deg}° variant"
            )
        return cls(counts[variant], unit_mm, baud_rate, realtime_indices)

    @property
    def resolution_deg(self) -> float:
        return VARIANT_BY_COUNT[self.count][1]

    @property
    def turns_per_telegram(self) -> int:
        """Mirror turns between telegrams of continuous output (§8): the fewest possible."""
        interval = scan_interval_s(self.baud_rate, self.count, self.resolution_deg, True)
        return round(interval / TURN_S)


def implausibility(
    scan: Scan, limits: ScanLimits, realtime_indices: bool | None = None
) -> Implausible | None:
    """The first rule a scan breaks that needs no other scan, or None if it breaks none.

    ``realtime_indices`` overrides ``limits.realtime_indices`` (a stream's learnt choice).
    """
    if len(scan.raw) != limits.count or scan.partial:
        return Implausible.COUNT
    if scan.count_word is not None and scan.count_word & ~(_COUNT_BITS | 3 << _UNIT_SHIFT):
        return Implausible.COUNT
    indices = limits.realtime_indices if realtime_indices is None else realtime_indices
    if indices is not None and indices != (scan.scan_index is not None):
        return Implausible.LENGTH
    if (scan.unit_m == 0.001) != limits.unit_mm:
        return Implausible.UNIT
    mask = DISTANCE_MASK[scan.measuring_mode]
    shift = FLAG_SHIFT[scan.measuring_mode]
    raw = scan.raw.astype(np.int64)
    if np.any(raw & ~(mask | (0xFFFF >> shift << shift))):
        return Implausible.FLAGS
    max_m = MODE_MAX_RANGE_M[scan.measuring_mode] if limits.unit_mm else CM_MAX_RANGE_M
    longest = min(mask - 9, math.floor(max_m * RANGE_MARGIN / scan.unit_m + 1e-9))
    gap = mask - (raw & mask)
    coded = np.isin(gap, _DOCUMENTED_GAPS)
    if np.any(~coded & ((raw & mask) > longest)):
        return Implausible.RANGE
    if scan.status & 0x07 > 4:
        return Implausible.STATUS
    return None


@dataclass(frozen=True)
class _Mark:
    """A scan's place in the sequence: its turn count since the anchor epoch began."""

    turn: int
    scan_index: int
    telegram_index: int
    stamp_s: float | None


class ScanCheck:
    """The plausibility rules for the scans of one stream, fed in order (thin: the state).

    The sequence rule compares each scan with the last accepted one, so a corrupted telegram is
    rejected alone and the good ones after it are kept; gaps from lost telegrams are allowed.
    The host stamps place the scan index (the mirror-turn counter mod 256) in time: a scan
    measured earlier than the host clock allows, relative to the earliest arrival seen in the
    last ``window`` scans, is rejected. Two consecutive rejected scans that agree with each
    other start the sequence anew (the sensor was reset or the stream restarted).
    ``rejected`` counts the rejections by reason.
    """

    def __init__(self, limits: ScanLimits, window: int = 64) -> None:
        self.limits = limits
        self.accepted = 0
        self.rejected: dict[str, int] = {}
        self._indices = limits.realtime_indices
        self._turns = limits.turns_per_telegram
        self._anchor: _Mark | None = None
        self._candidate: _Mark | None = None
        self._former: _Mark | None = None  # the anchor before a telegram counter restart
        self._arrivals: deque[float] = deque(maxlen=window)  # stamp − turn·T of accepted scans

    def check(self, scan: Scan) -> Implausible | None:
        """Why ``scan`` is implausible after the scans before it, or None (it is accepted)."""
        reason = implausibility(scan, self.limits, self._indices)
        if reason is None and scan.scan_index is not None and scan.telegram_index is not None:
            reason = self._sequence(scan)
        if reason is None:
            self.accepted += 1
            if self._indices is None:
                self._indices = scan.scan_index is not None
        else:
            self.rejected[reason.value] = self.rejected.get(reason.value, 0) + 1
        return reason

    def copy(self) -> ScanCheck:
        """An independent copy: what it is fed next does not change this one."""
        twin = ScanCheck(self.limits, self._arrivals.maxlen or 64)
        twin.__dict__.update(self.__dict__)
        twin.rejected = dict(self.rejected)
        twin._arrivals = deque(self._arrivals, maxlen=self._arrivals.maxlen)
        return twin

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def _start(self, scan: Scan) -> None:
        self._anchor = _Mark(0, int(scan.scan_index or 0), int(scan.telegram_index or 0),
                             scan.stamp_s)  # fmt: skip
        self._candidate = self._former = None
        self._arrivals.clear()
        if scan.stamp_s is not None:
            self._arrivals.append(scan.stamp_s)

    def _sequence(self, scan: Scan) -> Implausible | None:
        if self._anchor is None:
            self._start(scan)
            return None
        earliest = min(self._arrivals) if self._arrivals else None
        before = self._anchor
        turn = self._follows(before, scan, earliest)
        if turn is None and self._former is not None:
            before = self._former  # the telegram counter had not restarted after all
            turn = self._follows(before, scan, earliest)
        if turn is not None:
            restarted = scan.telegram_index == 0 and before.telegram_index != 255
            self._former = before if restarted else None
            self._anchor = _Mark(turn, int(scan.scan_index or 0), int(scan.telegram_index or 0),
                                 scan.stamp_s)  # fmt: skip
            self._candidate = None
            if scan.stamp_s is not None:
                self._arrivals.append(scan.stamp_s - turn * TURN_S)
            return None
        candidate = self._candidate
        if candidate is not None and self._follows(candidate, scan, candidate.stamp_s) is not None:
            self._start(scan)
            return None
        self._candidate = _Mark(0, int(scan.scan_index or 0), int(scan.telegram_index or 0),
                                scan.stamp_s)  # fmt: skip
        return Implausible.SEQUENCE

    def _follows(self, before: _Mark, scan: Scan, earliest_s: float | None) -> int | None:
        """The scan's turn count if it can follow ``before``, else None.

        ``earliest_s`` is the earliest arrival (stamp − turn·T) seen so far in this epoch.
        """
        telegrams = (int(scan.telegram_index or 0) - before.telegram_index) % 256
        if scan.telegram_index == 0:
            # A telegram counter that starts again from 0 needs one interval at least (the
            # simulator restarts it with every chunk of scans it writes to a capture).
            telegrams = 1
        if telegrams == 0:
            return None  # the same telegram index twice
        fewest = self._turns * telegrams  # a telegram leaves at most every K turns (§8)
        step = (int(scan.scan_index or 0) - before.scan_index) % 256
        if scan.stamp_s is None or before.stamp_s is None or earliest_s is None:
            # No host clock: allow up to one more lost scan per telegram (§11).
            wraps = max(0, math.ceil((fewest - step) / 256))
            turns = step + 256 * wraps
            return before.turn + turns if turns <= (self._turns + 1) * telegrams else None
        # Unwrap the turn counter: the fewest turns that the telegram index needs and that have
        # the scan arrive at most late_s after the earliest arrival.
        lower = max(fewest, (scan.stamp_s - earliest_s - self.limits.late_s) / TURN_S - before.turn)
        turns = step + 256 * max(0, math.ceil((lower - step) / 256))
        arrival = scan.stamp_s - (before.turn + turns) * TURN_S
        if arrival < earliest_s - self.limits.early_s:
            return None  # measured later than it arrived: the counter ran ahead
        return before.turn + turns
