"""Family 2: damaged datasets for batch, isam, evaluate and dataset check.

``mission.yaml``, ``events.jsonl``, the captures, the odometry, the ground truth and
``world.yaml``: each damage is one line naming the file (``dataset check`` lists it on stdout and
exits 2), and damage inside a capture that the stream parser can skip is counted, not fatal.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.estimation.app.cli.malformed import (
    Case,
    Guarded,
    Outcome,
    Setup,
    Workspace,
    cases_param,
    copy,
    directory,
    edit,
    edit_text,
    execute,
    fifo,
    json_lines,
    remove,
    run_guarded,
    simulated_dataset,
    symlink,
    workspace,
    write,
)

MISSION = "{ds}/mission.yaml"
EVENTS = "{ds}/events.jsonl"
CAP = "{ds}/robots/a/lms.cap"
ODOMETRY = "{ds}/robots/b/odometry.tum"
RUN = {
    "batch": ("batch", "{ds}"),
    "isam": ("isam", "{ds}"),
    "evaluate": ("evaluate", "{ds}"),
    "check": ("dataset", "check", "{ds}"),
}
GOOD_ROBOTS = (
    "robots:\n- {name: a, start: [2.0, 3.5, 20.0]}\n- {name: b, start: [3.5, 5.75, 220]}\n"
)


def mission_robots(text: str) -> Setup:
    """mission.yaml with its robots list replaced by ``text`` (the rest kept)."""

    def change(doc: str) -> str:
        head, _, rest = doc.partition("robots:\n")
        tail = rest[rest.index("plan:") :]
        return head + text + tail

    return edit_text(MISSION, change)


def mission_line(line: str) -> Setup:
    """mission.yaml with one top-level key (and its block) replaced by ``line``."""
    key = line.split(":", 1)[0]

    def change(doc: str) -> str:
        lines = doc.splitlines(keepends=True)
        start = next(n for n, x in enumerate(lines) if x.startswith(key + ":"))
        end = next((n for n in range(start + 1, len(lines)) if lines[n][:1] not in " -"),
                   len(lines))  # fmt: skip
        return "".join(lines[:start]) + line + "\n" + "".join(lines[end:])

    return edit_text(MISSION, change)


def first_of(kind: str, change: Any) -> Setup:
    """events.jsonl with ``change`` applied to the first event of ``kind`` (a dict, in place)."""

    def apply(rows: list[dict[str, Any]]) -> list[Any]:
        row = next(r for r in rows if r["event"] == kind)
        change(row)
        return rows

    return json_lines(EVENTS, apply)


def raw_events(change: Any) -> Setup:
    """events.jsonl rewritten as text: ``change`` gets and returns its lines."""
    return edit_text(EVENTS, lambda t: "".join(x + "\n" for x in change(t.splitlines())))


def _dwell_line(lines: list[str]) -> int:
    return next(n for n, x in enumerate(lines) if '"dwell"' in x)


def replace_dwell(text: str) -> Setup:
    def change(lines: list[str]) -> list[str]:
        lines[_dwell_line(lines)] = text
        return lines

    return raw_events(change)


def capture_body(data: bytes) -> tuple[int, bytes]:
    """(offset of the first record, the bytes) of a capture."""
    first = data.index(b"\n", data.index(b"\n") + 1) + 1
    return first, data


def overwrite_middle(fraction: float, size: int, random: bool) -> Setup:
    def change(data: bytes) -> bytes:
        start, _ = capture_body(data)
        at = start + int((len(data) - start) * fraction)
        fill = np.random.default_rng(7).bytes(size) if random else bytes(size)
        return data[:at] + fill + data[at + size :]

    return edit(CAP, change)


def inside_record(k: int, size: int) -> Setup:
    """Random bytes inside the body of record ``k`` (its header intact)."""

    def change(data: bytes) -> bytes:
        pos, _ = capture_body(data)
        for _ in range(k):
            pos += 12 + struct.unpack_from("<dI", data, pos)[1]
        at = pos + 12 + 20
        assert struct.unpack_from("<dI", data, pos)[1] > 20 + size
        return data[:at] + np.random.default_rng(5).bytes(size) + data[at + size :]

    return edit(CAP, change)


def plain_dump(data: bytes) -> bytes:
    """The record bodies of a capture without header and framing: a plain binary dump."""
    pos, _ = capture_body(data)
    out = bytearray()
    while pos + 12 <= len(data):
        _, size = struct.unpack_from("<dI", data, pos)
        out += data[pos + 12 : pos + 12 + size]
        pos += 12 + size
    return bytes(out)


def tum_line(n: int, text: str) -> Setup:
    """odometry.tum with its n-th pose line replaced by ``text``."""

    def change(doc: str) -> str:
        lines = doc.splitlines()
        poses = [k for k, x in enumerate(lines) if x and not x.startswith("#")]
        lines[poses[n]] = text
        return "\n".join(lines) + "\n"

    return edit_text(ODOMETRY, change)


def report(ws: Workspace) -> dict[str, Any]:
    return json.loads((ws.result / "report.json").read_text())


def counted(*keys: str) -> Any:
    """A check: robot a's report counts damage under one of ``keys``; both robots have poses."""

    def check(ws: Workspace, outcome: Outcome) -> None:
        robots = report(ws)["robots"]
        assert sum(robots["a"][k] for k in keys) > 0, robots["a"]
        assert (robots["a"]["poses"], robots["b"]["poses"]) == (3, 4), robots

    return check


def telegrams_lost(lost: int) -> Any:
    """A check: robot a's report has ``lost`` telegrams fewer than the intact run's and counts
    the bytes of the records lost to damaged record headers; both robots have poses."""

    def check(ws: Workspace, outcome: Outcome) -> None:
        intact = json.loads((ws.tmp / "intact.json").read_text())["robots"]["a"]
        robots = report(ws)["robots"]
        assert robots["a"]["telegrams"] == intact["telegrams"] - lost, robots["a"]
        assert intact["corrupt_bytes"] == 0
        assert robots["a"]["corrupt_bytes"] >= 4096, robots["a"]
        assert (robots["a"]["poses"], robots["b"]["poses"]) == (3, 4), robots

    return check


def cases(damage: str, setups: list[Setup], outcomes: dict[str, str], family: str) -> list[Case]:
    """One case per command: outcome ``"!pattern"`` is an error line, ``"?pattern"`` a dataset
    check report, ``"=pattern"`` success (stdout)."""
    made = []
    for command, expected in outcomes.items():
        kind, pattern = expected[0], expected[1:]
        made.append(Case(family, f"{command}: {damage}", RUN[command], setup=tuple(setups),
                         error=pattern if kind == "!" else None,
                         problem=pattern if kind == "?" else None,
                         ok=pattern if kind == "=" else None))  # fmt: skip
    return made


def everywhere(error: str, report_: str | None = None, evaluate: bool = True) -> dict[str, str]:
    found = {"batch": "!" + error, "isam": "!" + error, "check": "?" + (report_ or error)}
    if evaluate:
        found["evaluate"] = "!" + error
    return found


M = "mission"
MISSION_CASES = [
    *cases("robots missing", [mission_robots("")], everywhere(
        r"mission\.yaml: not a mission \(no robots\)",
        r"error: mission\.yaml: robots: required key is missing"), M),
    *cases("robots empty", [mission_robots("robots: []\n")],
           everywhere(r"mission\.yaml: robots: must be a list"), M),
    *cases("robots a mapping", [mission_robots("robots: {a: [0, 0, 0]}\n")],
           everywhere(r"mission\.yaml: robots: must be a list"), M),
    *cases("robot named ../../x", [mission_robots(GOOD_ROBOTS.replace("name: b", "name: ../../x"))],
           everywhere(r"robots\[1\]: name must be one lowercase letter a-z, got '\.\./\.\./x'"), M),
    *cases("robot named A", [mission_robots(GOOD_ROBOTS.replace("name: b", "name: A"))],
           everywhere(r"robots\[1\]: name must be one lowercase letter"), M),
    *cases("robot named by a number", [mission_robots(GOOD_ROBOTS.replace("name: b", "name: 7"))],
           everywhere(r"robots\[1\]: name must be one lowercase letter"), M),
    *cases("duplicate robots", [mission_robots(GOOD_ROBOTS.replace("name: b", "name: a"))],
           everywhere(r"robots\[1\]: robot 'a' is listed twice"), M),
    *cases("start of two numbers", [mission_robots(GOOD_ROBOTS.replace("3.5, 5.75, 220", "1, 2"))],
           everywhere(r"robots\[1\]: start must be \[x_m, y_m, yaw_deg\]"), M),
    *cases("start NaN", [mission_robots(GOOD_ROBOTS.replace("3.5, 5.75", "3.5, .nan"))],
           everywhere(r"robots\[1\]: start must be"), M),
    *cases("start text", [mission_robots(GOOD_ROBOTS.replace("3.5, 5.75", "north, 5.75"))],
           everywhere(r"robots\[1\]: start must be"), M),
    *cases("start missing", [mission_robots(GOOD_ROBOTS.replace(", start: [3.5, 5.75, 220]", ""))],
           everywhere(r"robots\[1\]: start must be"), M),
    *cases("robot entry a string", [mission_robots("robots:\n- a\n- b\n")],
           everywhere(r"robots\[0\]: must be a mapping"), M),
    *cases("config not a mapping", [mission_line("config: [1, 2]")],
           everywhere(r"mission\.yaml: config: must be a mapping"), M),
    *cases("config unknown key", [mission_line("config: {grid: {bogus: 1}}")],
           everywhere(r"grid\.bogus: unknown key"), M),
    *cases("config NaN", [mission_line("config: {mirror: {period_s: .nan}}")],
           everywhere(r"mirror\.period_s: .*finite"), M),
    *cases("binary", [write(MISSION, bytes(range(256)))], everywhere(r"mission\.yaml: not UTF-8",
           r"error: mission\.yaml: not UTF-8"), M),
    *cases("FIFO", [fifo(MISSION)], everywhere(r"mission\.yaml: not a regular file",
           r"error: mission\.yaml: not a regular file"), M),
    *cases("a directory", [directory(MISSION)], everywhere(r"mission\.yaml",
           r"error: mission\.yaml: is a directory"), M),
    *cases("missing", [remove(MISSION)], everywhere(r"not a coopmap dataset \(mission\.yaml is "
           r"missing\)", r"error: mission\.yaml: missing"), M),
    *cases("a list", [write(MISSION, "- robots\n")],
           everywhere(r"expected a YAML mapping at the top level"), M),
    *cases("an alias", [write(MISSION, "r: &r {name: a, start: [0, 0, 0]}\nrobots: [*r]\n")],
           everywhere(r"aliases \(\*name\) are not allowed"), M),
    *cases("malformed YAML", [write(MISSION, "robots: [\n")],
           everywhere(r"mission\.yaml: malformed YAML"), M),
]  # fmt: skip


def sparse(rel: str, size: int) -> Setup:
    def setup(ws: Workspace) -> None:
        with open(rel.format(**ws.fields()), "r+b") as handle:
            handle.truncate(size)

    return setup


E = "events"
EVENT_CASES = [
    *cases("dwell lacking end_s", [first_of("dwell", lambda r: r.pop("end_s"))],
           everywhere(r"events\.jsonl:3: dwell: end_s must be a number"), E),
    *cases("dwell ending before it starts", [first_of("dwell", lambda r: r.update(end_s=-1))],
           everywhere(r"events\.jsonl:3: dwell: end_s must be a number >= t_s"), E),
    *cases("t_s not a number", [first_of("dwell", lambda r: r.update(t_s="soon"))],
           everywhere(r"events\.jsonl:3: t_s must be a finite number, got 'soon'"), E),
    *cases("t_s NaN", [replace_dwell('{"t_s": NaN, "event": "dwell", "end_s": 31, '
                                     '"poses": {"a": 0, "b": 0}}')],
           everywhere(r"events\.jsonl:3: t_s must be a finite number, got nan"), E),
    *cases("t_s Infinity", [first_of("move", lambda r: r.update(t_s=float("inf")))],
           everywhere(r"events\.jsonl:5: t_s must be a finite number"), E),
    *cases("t_s missing", [first_of("dwell", lambda r: r.pop("t_s"))],
           everywhere(r"events\.jsonl:3: an event needs 'event' and 't_s'"), E),
    *cases("dwell poses lack a robot", [first_of("dwell", lambda r: r["poses"].pop("b"))],
           everywhere(r"events\.jsonl:3: dwell: poses must give the pose index of every robot"),
           E),
    *cases("dwell poses an extra robot", [first_of("dwell", lambda r: r["poses"].update(c=0))],
           everywhere(r"events\.jsonl:3: dwell: poses must give"), E),
    *cases("dwell pose index negative", [first_of("dwell", lambda r: r["poses"].update(a=-1))],
           everywhere(r"events\.jsonl:3: dwell: poses\.a must be an index"), E),
    *cases("dwell poses a list", [first_of("dwell", lambda r: r.update(poses=[0, 0]))],
           everywhere(r"events\.jsonl:3: dwell: poses must give"), E),
    *cases("reference not in the mission", [first_of("dwell", lambda r: r.update(reference="z"))],
           everywhere(r"events\.jsonl:3: dwell: reference 'z' is not one of the mission's robots"),
           E),
    *cases("mapper not in the mission", [first_of("dwell", lambda r: r.update(mapper="../x"))],
           everywhere(r"events\.jsonl:3: dwell: mapper '\.\./x' is not one of"), E),
    *cases("move to_index not from_index+1", [first_of("move", lambda r: r.update(to_index=3))],
           everywhere(r"events\.jsonl:5: move: to_index must be from_index \+ 1"), E),
    *cases("move index a boolean", [first_of("move", lambda r: r.update(from_index=True))],
           everywhere(r"events\.jsonl:5: move: from_index must be an index"), E),
    *cases("move of an unknown robot", [first_of("move", lambda r: r.update(robot="q"))],
           everywhere(r"events\.jsonl:5: move of robot 'q', not one of the mission's robots"), E),
    *cases("move start_s after t_s", [first_of("move", lambda r: r.update(start_s=1e9))],
           everywhere(r"events\.jsonl:5: move: start_s must be a number <= t_s"), E),
    *cases("move start_s missing", [first_of("move", lambda r: r.pop("start_s"))],
           everywhere(r"events\.jsonl:5: move: start_s must be"), E),
    *cases("a line not JSON", [raw_events(lambda x: [*x[:3], "{t_s: 1, event", *x[3:]])],
           everywhere(r"events\.jsonl:4: not JSON"), E),
    *cases("a JSON list line", [raw_events(lambda x: [*x[:3], '[1, "dwell"]', *x[3:]])],
           everywhere(r"events\.jsonl:4: an event needs 'event' and 't_s'"), E),
    *cases("a JSON number line", [raw_events(lambda x: [*x[:3], "42", *x[3:]])],
           everywhere(r"events\.jsonl:4: an event needs"), E),
    *cases("deeply nested JSON", [raw_events(lambda x: [*x[:3], "[" * 100000, *x[3:]])],
           everywhere(r"events\.jsonl:4: not an event: JSON nested too deeply"), E),
    *cases("binary", [write(EVENTS, b"\x00\xff\xfe" * 300)],
           everywhere(r"events\.jsonl: not UTF-8"), E),
    *cases("FIFO", [fifo(EVENTS)], everywhere(r"events\.jsonl: not a regular file"), E),
    *cases("missing", [remove(EVENTS)], everywhere(r"events\.jsonl is missing",
           r"error: events\.jsonl: missing"), E),
    *cases("a directory", [directory(EVENTS)], everywhere(r"events\.jsonl",
           r"error: events\.jsonl: is a directory"), E),
    *cases("empty", [write(EVENTS, "")], {
        "batch": r"!no sweep in any dwell \(the dataset has no dwells\)",
        "check": r"?error: events\.jsonl: no dwell"}, E),
    *cases("no dwell", [json_lines(EVENTS, lambda rs: [r for r in rs if r["event"] != "dwell"])], {
        "batch": r"!no sweep in any dwell \(the dataset has no dwells\)",
        "isam": r"!no sweep in any dwell",
        "check": r"?error: events\.jsonl: no dwell"}, E),
    *cases("no sweep", [json_lines(EVENTS, lambda rs: [
        {**r, "end_s": r["t_s"] + 1} if r["event"] == "dwell" else r for r in rs])], {
        "batch": r"!no sweep in any dwell \(a0 \(dwell 2\): only \d+ scans in the dwell",
        "check": r"?error: events\.jsonl: no dwell yields a sweep"}, E),
    *cases("larger than 256 MB", [sparse(EVENTS, 300 * 2**20)],
           everywhere(r"events\.jsonl: 314,572,800 bytes, more than the 268,435,456"), E),
]  # fmt: skip


C = "capture"
CAPTURE_CASES = [
    *cases("missing", [remove(CAP)], {"batch": r"!robots/a/lms\.cap: no such file",
           "isam": r"!robots/a/lms\.cap: no such file",
           "check": r"?error: robots/a/lms\.cap: no such file"}, C),
    *cases("FIFO", [fifo(CAP)], {"batch": r"!robots/a/lms\.cap: not a regular file",
           "isam": r"!lms\.cap: not a regular file",
           "check": r"?error: robots/a/lms\.cap: not a regular file"}, C),
    *cases("a directory", [directory(CAP)], {"batch": r"!robots/a/lms\.cap: is a directory",
           "check": r"?error: robots/a/lms\.cap: is a directory"}, C),
    *cases("empty", [write(CAP, b"")], {"batch": r"!robots/a/lms\.cap: (no measured values|"
           r"a plain binary dump)", "check": r"?error: robots/a/lms\.cap"}, C),
    *cases("random bytes", [write(CAP, lambda: np.random.default_rng(1).bytes(200_000))], {
        "batch": r"!robots/a/lms\.cap: (no measured values|a plain binary dump)",
        "check": r"?error: robots/a/lms\.cap"}, C),
    *cases("truncated header", [edit(CAP, lambda b: b[:30])], {
        "batch": r"!robots/a/lms\.cap: capture header line is truncated",
        "check": r"?error: robots/a/lms\.cap: capture header line is truncated"}, C),
    *cases("magic line only", [edit(CAP, lambda b: b[:17])], {
        "batch": r"!robots/a/lms\.cap: capture header line is truncated"}, C),
    *cases("header not JSON", [edit(CAP, lambda b: b[:17] + b"{baud: fast\n" + b[b.index(
        b"\n", 17) + 1:])], {"batch": r"!robots/a/lms\.cap: capture header is not JSON",
        "check": r"?error: robots/a/lms\.cap: capture header is not JSON"}, C),
    *cases("header a JSON list", [edit(CAP, lambda b: b[:17] + b"[1, 2]\n" + b[b.index(
        b"\n", 17) + 1:])], {"batch": r"!robots/a/lms\.cap: capture header is not a JSON object"},
        C),
    *cases("header only", [edit(CAP, lambda b: b[: capture_body(b)[0]])], {
        "batch": r"!robots/a/lms\.cap: no measured values",
        "check": r"?error: robots/a/lms\.cap: no measured values"}, C),
    *cases("a plain dump without header", [edit(CAP, plain_dump)], {
        "batch": r"!robots/a/lms\.cap: a plain binary dump",
        "isam": r"!robots/a/lms\.cap: a plain binary dump",
        "check": r"?error: robots/a/lms\.cap: a plain binary dump"}, C),
    *cases("zeroed stretch in the middle", [overwrite_middle(0.4, 4096, random=False)], {
        "check": r"=(?s)warning: robots/a/lms\.cap: 4,294 bytes of records with damaged "
                 r"headers.*0 errors"}, C),
    *cases("random stretch in the middle", [overwrite_middle(0.6, 4096, random=True)], {
        "check": r"=(?s)warning: robots/a/lms\.cap: [\d,]+ bytes of records with damaged "
                 r"headers.*0 errors"}, C),
    *cases("random bytes inside one record", [inside_record(1500, 30)], {
        "check": r"=(?s)warning: robots/a/lms\.cap: .*(checksum failures|bytes skipped).*0 "
                 r"errors"}, C),
    *cases("last record cut short", [edit(CAP, lambda b: b[:-7])], {
        "check": r"=(?s)warning: robots/a/lms\.cap: .*bytes of a truncated last record"}, C),
]  # fmt: skip
# The successes run the whole pipeline: a few, each checking what report.json counted.
CAPTURE_CASES += [
    Case(C, "batch: zeroed stretch in the middle", RUN["batch"],
         setup=(copy("{ds}/result/report.json", "intact.json"),
                overwrite_middle(0.4, 4096, random=False)), ok=r"coopmap batch: 14 sweeps",
         check=telegrams_lost(19)),
    Case(C, "batch: random bytes inside one record", RUN["batch"],
         setup=(inside_record(1500, 30),), ok=r"coopmap batch: 14 sweeps",
         check=counted("bytes_skipped", "checksum_failures", "undecodable")),
    Case(C, "isam: last record cut short", ("isam", "{ds}", "--out", "{ds}/result"),
         setup=(edit(CAP, lambda b: b[:-7]),), ok=r"coopmap isam: \d+ events",
         check=counted("truncated_bytes")),
]  # fmt: skip

ODO = "odometry"
ODOMETRY_CASES = [
    *cases("missing", [remove(ODOMETRY)], {"batch": r"!robots/b/odometry\.tum: no such file",
           "check": r"?error: robots/b/odometry\.tum: no such file"}, ODO),
    *cases("FIFO", [fifo(ODOMETRY)], {"batch": r"!robots/b/odometry\.tum: not a regular file",
           "isam": r"!robots/b/odometry\.tum: not a regular file",
           "check": r"?error: robots/b/odometry\.tum: not a regular file"}, ODO),
    *cases("a directory", [directory(ODOMETRY)], {"batch": r"!robots/b/odometry\.tum: is a "
           r"directory", "check": r"?error: robots/b/odometry\.tum: is a directory"}, ODO),
    *cases("seven fields", [tum_line(3, "1.0 0 0 0 0 0 1")], {
        "batch": r"!odometry\.tum:\d+: TUM line needs 8 fields .*got 7",
        "check": r"?error: robots/b/odometry\.tum:\d+: TUM line needs 8 fields"}, ODO),
    *cases("nine fields", [tum_line(3, "0.3 0 0 0 0 0 0 1 9")], {
        "batch": r"!odometry\.tum:\d+: TUM line needs 8 fields .*got 9"}, ODO),
    *cases("NaN", [tum_line(3, "0.3 nan 0 0 0 0 0 1")], {
        "batch": r"!odometry\.tum:\d+: TUM line: non-finite value",
        "isam": r"!odometry\.tum:\d+: TUM line: non-finite value",
        "check": r"?error: robots/b/odometry\.tum:\d+: TUM line: non-finite"}, ODO),
    *cases("a word", [tum_line(3, "0.3 x 0 0 0 0 0 1")], {
        "batch": r"!odometry\.tum:\d+: TUM line: not a number"}, ODO),
    *cases("non-unit quaternion", [tum_line(3, "0.3 0 0 0 0 0 0 2")], {
        "batch": r"!odometry\.tum:\d+: quaternion norm is 2, not 1",
        "check": r"?error: robots/b/odometry\.tum:\d+: quaternion norm is 2"}, ODO),
    *cases("tilted quaternion", [tum_line(3, "0.3 0 0 0 0.7071068 0 0 0.7071068")], {
        "batch": r"!odometry\.tum:\d+: pose is tilted"}, ODO),
    *cases("time going back", [tum_line(5, "0.0 0 0 0 0 0 0 1")], {
        "batch": r"!odometry\.tum:\d+: timestamp 0\.0 goes back",
        "check": r"?error: robots/b/odometry\.tum:\d+: timestamp 0\.0 goes back"}, ODO),
    *cases("empty", [write(ODOMETRY, "")], {"batch": r"!robots/b/odometry\.tum: no poses",
           "check": r"?error: robots/b/odometry\.tum: no poses"}, ODO),
    *cases("comments only", [write(ODOMETRY, "# t x y z qx qy qz qw\n")], {
        "batch": r"!robots/b/odometry\.tum: no poses"}, ODO),
    *cases("binary", [write(ODOMETRY, b"\xff\xfe\x00" * 100)], {
        "batch": r"!robots/b/odometry\.tum: not a readable text file",
        "check": r"?error: robots/b/odometry\.tum: not a readable text file"}, ODO),
    *cases("one endless line", [write(ODOMETRY, b"1" * (2**20))], {
        "batch": r"!robots/b/odometry\.tum:1: (a line longer than|TUM line)",
        "check": r"?error: robots/b/odometry\.tum:1: "}, ODO),
]  # fmt: skip

GT = "{ds}/ground_truth/a.tum"
WORLD = "{ds}/world.yaml"
T = "truth"
TRUTH_CASES = [
    Case(T, "evaluate: ground truth missing", RUN["evaluate"], setup=(remove(GT),),
         error=r"no ground truth for robot 'a' \(a\.tum\)"),
    Case(T, "evaluate: ground truth FIFO", RUN["evaluate"], setup=(fifo(GT),),
         error=r"ground_truth/a\.tum: not a regular file"),
    Case(T, "evaluate: ground truth a directory", RUN["evaluate"], setup=(directory(GT),),
         error=r"no ground truth for robot 'a'|ground_truth/a\.tum: is a directory"),
    Case(T, "evaluate: ground truth NaN", RUN["evaluate"],
         setup=(edit_text(GT, lambda t: t.replace("\n0.", "\nnan ", 1)),),
         error=r"ground_truth/a\.tum:\d+: TUM line"),
    Case(T, "evaluate: ground truth empty", RUN["evaluate"], setup=(write(GT, ""),),
         error=r"ground_truth/a\.tum: no poses"),
    Case(T, "evaluate: ground truth going back", RUN["evaluate"],
         setup=(edit_text(GT, lambda t: t + "0.0 0 0 0 0 0 0 1\n"),),
         error=r"ground_truth/a\.tum:\d+: timestamp 0\.0 goes back"),
    Case(T, "evaluate: world.yaml missing", RUN["evaluate"], setup=(remove(WORLD),),
         error=r"world\.yaml: no such file"),
    Case(T, "evaluate: world.yaml FIFO", RUN["evaluate"], setup=(fifo(WORLD),),
         error=r"world\.yaml: not a regular file"),
    Case(T, "evaluate: world.yaml malformed", RUN["evaluate"], setup=(write(WORLD, "rooms: [\n"),),
         error=r"world\.yaml: malformed YAML"),
    Case(T, "evaluate: world.yaml a list", RUN["evaluate"], setup=(write(WORLD, "- room\n"),),
         error=r"world\.yaml: expected a YAML mapping"),
    Case(T, "evaluate: world.yaml without rooms", RUN["evaluate"], setup=(write(WORLD, "name: x\n"),),
         error=r"world\.yaml: .*rooms: required key is missing"),
    Case(T, "check: ground truth NaN", RUN["check"],
         setup=(edit_text(GT, lambda t: t.replace("\n0.", "\nnan ", 1)),),
         problem=r"error: ground_truth/a\.tum:\d+: TUM line"),
    Case(T, "check: world.yaml malformed", RUN["check"], setup=(write(WORLD, "rooms: [\n"),),
         problem=r"error: world\.yaml: malformed YAML"),
    Case(T, "check: world.yaml FIFO", RUN["check"], setup=(fifo(WORLD),),
         problem=r"error: world\.yaml: not a regular file"),
]  # fmt: skip

GUARDED = [
    Case(ODO, "batch: odometry is /dev/zero", RUN["batch"], guarded=True,
         setup=(symlink(ODOMETRY, "/dev/zero"),), error=r"odometry\.tum: not a regular file"),
    Case(C, "batch: capture is /dev/zero", RUN["batch"], guarded=True,
         setup=(symlink(CAP, "/dev/zero"),), error=r"lms\.cap: not a regular file"),
    Case(M, "batch: mission.yaml is /dev/zero", RUN["batch"], guarded=True,
         setup=(symlink(MISSION, "/dev/zero"),), error=r"mission\.yaml"),
    Case(E, "batch: events.jsonl is /dev/zero", RUN["batch"], guarded=True,
         setup=(symlink(EVENTS, "/dev/zero"),), error=r"events\.jsonl: not a regular file"),
    Case(T, "evaluate: ground truth is /dev/zero", RUN["evaluate"], guarded=True,
         setup=(symlink(GT, "/dev/zero"),), error=r"a\.tum: not a regular file"),
    Case(T, "check: world.yaml is /dev/zero", RUN["check"], guarded=True,
         setup=(symlink(WORLD, "/dev/zero"),), problem=r"error: world\.yaml: not a regular file"),
]  # fmt: skip

CASES = MISSION_CASES + EVENT_CASES + CAPTURE_CASES + ODOMETRY_CASES + TRUTH_CASES


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory, essex_simulated: Path) -> Path:
    return simulated_dataset(tmp_path_factory, essex_simulated)


@pytest.fixture(scope="module")
def guarded(tmp_path_factory: pytest.TempPathFactory, dataset: Path) -> Guarded:
    return run_guarded(GUARDED, tmp_path_factory.mktemp("guarded"), dataset)


@cases_param(CASES)
def test_a_damaged_dataset_is_one_line_or_counted(
    case: Case, tmp_path: Path, dataset: Path
) -> None:
    execute(case, workspace(case, tmp_path, dataset))


@cases_param(GUARDED)
def test_a_device_in_a_dataset_is_refused_unread(case: Case, guarded: Guarded) -> None:
    execute(case, guarded.workspaces[case.id], guarded.outcomes[case.id])
