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
from dataclasses import dataclass

import numpy as np
from numba import njit

from sensors.lms200.protocol.scan import VARIANT_BY_COUNT, Scan, ScanBatch, scan_interval_s
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
    "ScanRules",
    "implausibility",
    "scan_rules",
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


#: Implausible by the code the kernels use (0: plausible).
_REASONS = (None, *Implausible)
_COUNT, _LENGTH, _UNIT, _RANGE, _FLAGS, _STATUS, _SEQUENCE = range(1, 8)
# Gaps up to 8 that are documented special codes; row 9 stands for every larger gap.
_CODED_GAP = np.zeros(10, dtype=np.bool_)
_CODED_GAP[list(_DOCUMENTED_GAPS)] = True


@dataclass(frozen=True)
class ScanRules:
    """The rules that need no other scan, judged for many scans at once.

    ``first`` is the first rule before the index-bytes rule that a scan breaks (``count``, or
    0), ``then`` the first one after it (``unit``, ``flags``, ``range``, ``status``, or 0);
    ``indexed`` whether it carries real-time indices.
    """

    first: np.ndarray  # (n,) int64 reason code
    then: np.ndarray  # (n,) int64 reason code
    indexed: np.ndarray  # (n,) bool


@njit(cache=True)
def _value_rules(  # pragma: no cover - numba
    raw: np.ndarray, starts: np.ndarray, stops: np.ndarray, mask: int, stray_bits: int,
    longest: np.ndarray, coded_gap: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Per scan (values ``raw[starts[k]:stops[k]]``): whether a value sets a bit the mode
    never sets, and whether one is a distance beyond ``longest[k]`` that is no special code."""
    stray = np.zeros(len(starts), np.bool_)
    beyond = np.zeros(len(starts), np.bool_)
    for k in range(len(starts)):
        for v in range(starts[k], stops[k]):
            word = np.int64(raw[v])
            distance = word & mask
            if word & stray_bits:
                stray[k] = True
            if distance > longest[k] and not coded_gap[min(int(mask - distance), 9)]:
                beyond[k] = True
    return stray, beyond


def scan_rules(
    batch: ScanBatch, rows: np.ndarray, limits: ScanLimits, unit_m: np.ndarray | None = None
) -> ScanRules:
    """:class:`ScanRules` of the well-formed telegrams ``rows`` of ``batch`` (§6).

    ``unit_m`` overrides the unit the count words give (a :class:`Scan` built by hand).
    """
    mode = batch.measuring_mode
    mask, shift = DISTANCE_MASK[mode], FLAG_SHIFT[mode]
    word = batch.count_word[rows]
    units = np.where(word >> _UNIT_SHIFT == 1, 0.001, 0.01) if unit_m is None else unit_m
    starts, stops = batch.bounds[rows], batch.bounds[rows + 1]
    max_m = MODE_MAX_RANGE_M[mode] if limits.unit_mm else CM_MAX_RANGE_M
    distinct, which = np.unique(units, return_inverse=True)  # two at most: mm and cm
    longest = np.array(
        [min(mask - 9, math.floor(max_m * RANGE_MARGIN / float(u) + 1e-9)) for u in distinct],
        np.int64,
    )[which.reshape(-1)]
    stray, beyond = _value_rules(batch.raw, starts, stops, mask,
                                 0xFFFF & ~(mask | (0xFFFF >> shift << shift)), longest,
                                 _CODED_GAP)  # fmt: skip
    partial = word & 0x2000 != 0
    first = np.where(
        (stops - starts != limits.count)
        | partial
        | (word & ~(_COUNT_BITS | 3 << _UNIT_SHIFT) != 0),
        _COUNT,
        0,
    )
    then = np.select(
        [(units == 0.001) != limits.unit_mm, stray, beyond, batch.status[rows] & 0x07 > 4],
        [_UNIT, _FLAGS, _RANGE, _STATUS],
        0,
    )
    return ScanRules(first, then, batch.scan_index[rows] >= 0)


def _batch_of(scan: Scan) -> ScanBatch:
    """One :class:`Scan` as a batch of one, for the rules."""
    count_word = scan.count_word
    if count_word is None:  # built by hand: no stray bits, the fields say the rest
        count_word = (len(scan.raw) & _COUNT_BITS) | (0x2000 if scan.partial else 0)
    return ScanBatch(
        errors=np.zeros(1, np.int8),
        count_word=np.array([count_word], np.int64),
        bounds=np.array([0, len(scan.raw)], np.int64),
        scan_index=np.array([-1 if scan.scan_index is None else scan.scan_index], np.int64),
        telegram_index=np.array(
            [-1 if scan.telegram_index is None else scan.telegram_index], np.int64
        ),
        status=np.array([scan.status], np.int64),
        raw=np.asarray(scan.raw, np.uint16),
        ranges_m=scan.ranges_m,
        flags=scan.flags,
        code=scan.code,
        measuring_mode=scan.measuring_mode,
    )


def implausibility(
    scan: Scan, limits: ScanLimits, realtime_indices: bool | None = None
) -> Implausible | None:
    """The first rule a scan breaks that needs no other scan, or None if it breaks none.

    ``realtime_indices`` overrides ``limits.realtime_indices`` (a stream's learnt choice).
    """
    rules = scan_rules(_batch_of(scan), np.zeros(1, np.int64), limits, np.array([scan.unit_m]))
    first = int(rules.first[0])
    if scan.partial and not first:
        first = _COUNT
    indices = limits.realtime_indices if realtime_indices is None else realtime_indices
    if not first and indices is not None and indices != (scan.scan_index is not None):
        first = _LENGTH
    return _REASONS[first or int(rules.then[0])]


# The sequence state of a ScanCheck, in arrays the kernel updates in place. Marks (rows: the
# anchor, the candidate, the anchor before a telegram counter restart) hold a scan's turn count
# since the epoch began, its indices and host stamp; ``_SET`` says whether the mark exists.
_ANCHOR, _CANDIDATE, _FORMER = 0, 1, 2
_TURN, _SCAN, _TELEGRAM, _STAMP, _STAMPED, _SET = range(6)
# The integer state: the index bytes (-1 not known yet, 0 without, 1 with), the arrivals seen
# in this epoch (stamp − turn·T, the last ``window`` of them kept in a ring).
_INDICES, _ARRIVALS = 0, 1


@njit(cache=True)
def _mark(marks: np.ndarray, row: int, turn: int, scan: np.ndarray, stamp: float) -> None:
    marks[row, _TURN] = turn  # pragma: no cover - numba
    marks[row, _SCAN] = scan[3]
    marks[row, _TELEGRAM] = scan[4]
    marks[row, _STAMP] = stamp
    marks[row, _STAMPED] = scan[5]
    marks[row, _SET] = 1.0


@njit(cache=True)
def _follows(  # pragma: no cover - numba
    marks: np.ndarray, row: int, scan: np.ndarray, stamp: float, earliest: float, timed: bool,
    spacing: np.ndarray,
) -> int:  # fmt: skip
    """The scan's turn count if it can follow mark ``row``, else -1 (ScanCheck._follows)."""
    turns_per, early_s, late_s = int(spacing[0]), spacing[1], spacing[2]
    before_turn = int(marks[row, _TURN])
    telegrams = (scan[4] - int(marks[row, _TELEGRAM])) % 256
    if scan[4] == 0:
        # A telegram counter that starts again from 0 needs one interval at least (the
        # simulator restarts it with every chunk of scans it writes to a capture).
        telegrams = 1
    if telegrams == 0:
        return -1  # the same telegram index twice
    fewest = turns_per * telegrams  # a telegram leaves at most every K turns (§8)
    step = (scan[3] - int(marks[row, _SCAN])) % 256
    if scan[5] == 0 or marks[row, _STAMPED] == 0.0 or not timed:
        # No host clock: allow up to one more lost scan per telegram (§11).
        wraps = max(0, math.ceil((fewest - step) / 256))
        turns = step + 256 * wraps
        return before_turn + turns if turns <= (turns_per + 1) * telegrams else -1
    # Unwrap the turn counter: the fewest turns that the telegram index needs and that have the
    # scan arrive at most late_s after the earliest arrival.
    lower = (stamp - earliest - late_s) / TURN_S - before_turn
    if not lower > fewest:
        lower = fewest
    turns = step + 256 * max(0, math.ceil((lower - step) / 256))
    arrival = stamp - (before_turn + turns) * TURN_S
    if arrival < earliest - early_s:
        return -1  # measured later than it arrived: the counter ran ahead
    return before_turn + turns


@njit(cache=True)
def _arrive(state: np.ndarray, arrivals: np.ndarray, value: float) -> None:
    arrivals[state[_ARRIVALS] % len(arrivals)] = value  # pragma: no cover - numba
    state[_ARRIVALS] += 1


@njit(cache=True)
def _start(  # pragma: no cover - numba
    marks: np.ndarray, state: np.ndarray, arrivals: np.ndarray, scan: np.ndarray, stamp: float
) -> None:
    _mark(marks, _ANCHOR, 0, scan, stamp)
    marks[_CANDIDATE, _SET] = 0.0
    marks[_FORMER, _SET] = 0.0
    state[_ARRIVALS] = 0
    if scan[5]:
        _arrive(state, arrivals, stamp)


@njit(cache=True)
def _sequence(  # pragma: no cover - numba
    marks: np.ndarray, state: np.ndarray, arrivals: np.ndarray, scan: np.ndarray, stamp: float,
    spacing: np.ndarray,
) -> int:  # fmt: skip
    if marks[_ANCHOR, _SET] == 0.0:
        _start(marks, state, arrivals, scan, stamp)
        return 0
    kept = min(state[_ARRIVALS], len(arrivals))
    timed = kept > 0
    earliest = arrivals[:kept].min() if timed else 0.0
    before = _ANCHOR
    turn = _follows(marks, before, scan, stamp, earliest, timed, spacing)
    if turn < 0 and marks[_FORMER, _SET] != 0.0:
        before = _FORMER  # the telegram counter had not restarted after all
        turn = _follows(marks, before, scan, stamp, earliest, timed, spacing)
    if turn >= 0:
        if scan[4] == 0 and marks[before, _TELEGRAM] != 255:
            marks[_FORMER] = marks[before]
        else:
            marks[_FORMER, _SET] = 0.0
        _mark(marks, _ANCHOR, turn, scan, stamp)
        marks[_CANDIDATE, _SET] = 0.0
        if scan[5]:
            _arrive(state, arrivals, stamp - turn * TURN_S)
        return 0
    if marks[_CANDIDATE, _SET] != 0.0:
        timed = marks[_CANDIDATE, _STAMPED] != 0.0
        earliest = marks[_CANDIDATE, _STAMP]
        if _follows(marks, _CANDIDATE, scan, stamp, earliest, timed, spacing) >= 0:
            _start(marks, state, arrivals, scan, stamp)
            return 0
    _mark(marks, _CANDIDATE, 0, scan, stamp)
    return _SEQUENCE


@njit(cache=True)
def _check_scans(  # pragma: no cover - numba
    scans: np.ndarray, stamps: np.ndarray, marks: np.ndarray, state: np.ndarray,
    arrivals: np.ndarray, spacing: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """ScanCheck.check of each scan in turn: its reason code (0: accepted).

    ``scans`` (n, 7) int64: first rule broken before the index-bytes rule, first one after
    it, has index bytes, scan index, telegram index, has a host stamp, and whether both indices
    are there (the sequence is checked); ``stamps`` (n,) the host stamps; ``spacing`` the
    telegram spacing: [turns per telegram, early_s, late_s].
    """
    reasons = np.zeros(len(scans), np.int8)
    for k in range(len(scans)):
        scan = scans[k]
        reason = scan[0]
        if reason == 0:
            learnt = state[_INDICES]
            reason = _LENGTH if learnt >= 0 and learnt != scan[2] else scan[1]
        if reason == 0 and scan[6]:
            reason = _sequence(marks, state, arrivals, scan, stamps[k], spacing)
        if reason == 0 and state[_INDICES] < 0:
            state[_INDICES] = scan[2]
        reasons[k] = reason
    return reasons


class ScanCheck:
    """The plausibility rules for the scans of one stream, fed in order (thin: the state).

    The sequence rule compares each scan with the last accepted one, so a corrupted telegram is
    rejected alone and the good ones after it are kept; gaps from lost telegrams are allowed.
    The host stamps place the scan index (the mirror-turn counter mod 256) in time: a scan
    measured earlier than the host clock allows, relative to the earliest arrival seen in the
    last ``window`` scans, is rejected. Two consecutive rejected scans that agree with each
    other start the sequence anew (the sensor was reset or the stream restarted).
    ``rejected`` counts the rejections by reason. :meth:`check_batch` judges many scans in one
    call, exactly as :meth:`check` one after the other.
    """

    def __init__(self, limits: ScanLimits, window: int = 64) -> None:
        self.limits = limits
        self.accepted = 0
        self.rejected: dict[str, int] = {}
        indices = limits.realtime_indices
        self._state = np.array([-1 if indices is None else int(indices), 0], np.int64)
        self._marks = np.zeros((3, 6))
        self._arrivals = np.zeros(window)
        self._spacing = np.array([limits.turns_per_telegram, limits.early_s, limits.late_s])

    def check(self, scan: Scan) -> Implausible | None:
        """Why ``scan`` is implausible after the scans before it, or None (it is accepted)."""
        batch = _batch_of(scan)
        rows = np.zeros(1, np.int64)
        rules = scan_rules(batch, rows, self.limits, np.array([scan.unit_m]))
        if scan.partial and not rules.first[0]:
            rules.first[0] = _COUNT
        sequenced = scan.scan_index is not None and scan.telegram_index is not None
        stamp = np.array([math.nan if scan.stamp_s is None else scan.stamp_s])
        reasons = self._judge(rules, batch, rows, stamp, np.array([scan.stamp_s is not None]),
                              np.array([sequenced]))  # fmt: skip
        return _REASONS[int(reasons[0])]

    def check_batch(
        self, batch: ScanBatch, rows: np.ndarray, stamps_s: np.ndarray, stamped: np.ndarray
    ) -> np.ndarray:
        """:meth:`check` of the well-formed telegrams ``rows`` of ``batch`` in order, received
        at ``stamps_s`` (where ``stamped``); (n,) bool: accepted."""
        rules = scan_rules(batch, rows, self.limits)
        reasons = self._judge(rules, batch, rows, stamps_s, stamped, rules.indexed)
        return np.asarray(reasons == 0)

    def _judge(
        self, rules: ScanRules, batch: ScanBatch, rows: np.ndarray, stamps_s: np.ndarray,
        stamped: np.ndarray, sequenced: np.ndarray,
    ) -> np.ndarray:  # fmt: skip
        scans = np.column_stack([
            rules.first, rules.then, rules.indexed, batch.scan_index[rows],
            batch.telegram_index[rows], stamped, sequenced,
        ]).astype(np.int64)  # fmt: skip
        reasons = _check_scans(scans, np.asarray(stamps_s, np.float64), self._marks,
                               self._state, self._arrivals, self._spacing)  # fmt: skip
        self.accepted += int(np.count_nonzero(reasons == 0))
        found, first, counts = np.unique(reasons, return_index=True, return_counts=True)
        for k in np.argsort(first):
            if found[k]:
                name = str(_REASONS[int(found[k])])
                self.rejected[name] = self.rejected.get(name, 0) + int(counts[k])
        return reasons

    def copy(self) -> ScanCheck:
        """An independent copy: what it is fed next does not change this one."""
        twin = ScanCheck(self.limits, len(self._arrivals))
        twin.accepted = self.accepted
        twin.rejected = dict(self.rejected)
        twin._state = self._state.copy()
        twin._marks = self._marks.copy()
        twin._arrivals = self._arrivals.copy()
        return twin

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())
