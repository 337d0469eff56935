"""Families 5 and 6: damaged worlds and missions (simulate, world show, lms emulate) and damaged
captures for ``lms decode``.

A world or mission error is one line naming the file and the key; a capture that the stream
parser can read past is decoded with its damage counted in the summary line.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tests.estimation.app.cli.malformed import (
    Case,
    Guarded,
    Setup,
    cases_param,
    directory,
    edit,
    execute,
    fifo,
    remove,
    run_guarded,
    workspace,
    write,
)

WORLD = "{tmp}/world.yaml"
MISSION = "{tmp}/mission.yaml"
ROOM = "{name: r, footprint: %s, ceiling_m: 2.6}"
SQUARE = "[[0, 0], [6, 0], [6, 5], [0, 5]]"
#: A mission on the world file beside it, with an explicit plan (no planning to wait for).
GOOD_MISSION = (
    "world: world.yaml\nseed: 1\nrobots:\n  - {name: a, start: [1, 1, 0]}\n"
    "  - {name: b, start: [2, 2, 90]}\nplan:\n  - {reference: a, mapper: b, scans: [[3, 2, 0]]}\n"
)
WORLD_COMMANDS = {
    "world-show": ("world", "show", WORLD, "--out", "{tmp}/w.png"),
    "simulate": ("simulate", MISSION, "--out", "{tmp}/ds"),
    "lms-emulate": (
        "lms",
        "emulate",
        "--world",
        WORLD,
        "--pose",
        "1",
        "1",
        "0",
        "--seconds",
        "0.1",
    ),
}


def world(text: str | bytes) -> Setup:
    return write(WORLD, text)


def rooms(*footprints: str) -> Setup:
    listed = "".join(f"  - {ROOM % f}\n" for f in footprints)
    return world(f"name: w\nrooms:\n{listed}")


def circle(n: int) -> str:
    angles = np.linspace(0, 2 * math.pi, n, endpoint=False)
    return "[" + ", ".join(f"[{3 + 2.5 * math.cos(a):.6f}, {2.5 + 2.5 * math.sin(a):.6f}]"
                           for a in angles) + "]"  # fmt: skip


#: (damage, setups, error pattern)
WORLD_DAMAGES = [
    ("malformed YAML", [world("rooms: [\n")], r"world\.yaml: malformed YAML at line"),
    ("self-intersecting footprint", [rooms("[[0, 0], [6, 5], [6, 0], [0, 5]]")],
     r"footprint .*(cross|intersect|simple)"),
    ("clockwise footprint", [rooms("[[0, 0], [0, 5], [6, 5], [6, 0]]")], r"counter-clockwise"),
    ("5000-vertex footprint", [rooms(circle(5000))], r"(4096|4,096)"),
    ("NaN vertex", [rooms("[[0, 0], [6, 0], [6, .nan], [0, 5]]")],
     r"rooms\[0\]\.footprint.*(finite|nan)"),
    ("two-vertex footprint", [rooms("[[0, 0], [6, 0]]")], r"rooms\[0\]\.footprint"),
    ("repeated vertex", [rooms("[[0, 0], [6, 0], [6, 0], [6, 5], [0, 5]]")],
     r"footprint vertices 1 and 2"),
    ("unknown world name", [], r"'nowhere' is neither a world file nor a built-in world"),
    ("a list", [world("- room\n")], r"world\.yaml: expected a YAML mapping at the top level"),
    ("no rooms", [world("name: w\n")], r"rooms: required key is missing"),
    ("empty rooms", [world("name: w\nrooms: []\n")], r"rooms"),
    ("FIFO", [fifo(WORLD)], r"world\.yaml: not a regular file"),
    ("a directory", [directory(WORLD)], r"world\.yaml: is a directory"),
    ("an alias", [world(f"f: &f {SQUARE}\nname: w\nrooms:\n  - {{name: r, footprint: *f, "
                        "ceiling_m: 2.6}\n")], r"aliases \(\*name\) are not allowed"),
    ("unknown key", [world(f"name: w\nwalls: 3\nrooms:\n  - {ROOM % SQUARE}\n")],
     r"walls: unknown key"),
    ("negative ceiling", [world(f"name: w\nrooms:\n  - {{name: r, footprint: {SQUARE}, "
                                "ceiling_m: -1}\n")], r"rooms\[0\]\.ceiling_m"),
    ("infinite ceiling", [world(f"name: w\nrooms:\n  - {{name: r, footprint: {SQUARE}, "
                                "ceiling_m: .inf}\n")], r"rooms\[0\]\.ceiling_m"),
    ("empty file", [world("")], r"rooms: required key is missing"),
    ("nested 20000 deep", [world("rooms: " + "[" * 20000)], r"nested more than 100 levels"),
    ("binary", [world(bytes(range(256)) * 3)], r"world\.yaml: not UTF-8"),
    ("box of NaN size", [world(f"name: w\nrooms:\n  - {ROOM % SQUARE}\nboxes:\n  - {{name: b, "
                               "center: [2, 2], size: [.nan, 1], z_m: [0, 1]}\n")],
     r"boxes\[0\]\.size"),
    ("cylinder of radius 0", [world(f"name: w\nrooms:\n  - {ROOM % SQUARE}\ncylinders:\n  - "
                                    "{name: c, center: [2, 2], radius_m: 0, z_m: [0, 1]}\n")],
     r"cylinders\[0\]\.radius_m"),
    ("opening on a wall that is not there", [world(
        f"name: w\nrooms:\n  - {{name: r, footprint: {SQUARE}, ceiling_m: 2.6, openings: "
        "[{wall: 9, from_m: 1, to_m: 2, bottom_m: 0, top_m: 2}]}\n")], r"wall 9|openings"),
]  # fmt: skip


def _world_case(command: str, args: tuple[str, ...], damage: str, setups: list[Setup],
                pattern: str) -> Case:  # fmt: skip
    if damage == "unknown world name":
        args = tuple("nowhere" if a == WORLD else a for a in args)
        setups = [write(MISSION, GOOD_MISSION.replace("world.yaml", "nowhere"))]
    elif command == "simulate":
        setups = [write(MISSION, GOOD_MISSION), *setups]
    return Case("world", f"{command}: {damage}", args, error=pattern, setup=tuple(setups))


WORLD_CASES = [
    _world_case(command, args, damage, setups, pattern)
    for command, args in WORLD_COMMANDS.items()
    for damage, setups, pattern in WORLD_DAMAGES
]
GOOD_WORLD = rooms(SQUARE)
SIMULATE = WORLD_COMMANDS["simulate"]


def mission(text: str) -> Setup:
    return write(MISSION, text)


def mission_edit(old: str, new: str) -> Setup:
    return mission(GOOD_MISSION.replace(old, new))


#: (damage, setups, error pattern)
MISSION_DAMAGES = [
    ("malformed YAML", [mission("robots: [\n")], r"mission\.yaml: malformed YAML"),
    ("step with an unknown reference", [mission_edit("reference: a", "reference: c")],
     r"plan\[0\]: reference 'c' is not one of the robots \['a', 'b'\]"),
    ("step with an unknown mapper", [mission_edit("mapper: b", "mapper: ../x")],
     r"plan\[0\]: mapper '\.\./x' is not one of the robots"),
    ("robot of a long name", [mission_edit("name: b", "name: robot2")], r"robots\[1\]\.name"),
    ("robot named ../../x", [mission_edit("name: b", "name: ../../x")], r"robots\[1\]\.name"),
    ("one robot only", [mission("world: world.yaml\nrobots:\n  - {name: a, start: [1, 1, 0]}\n"
                                "plan: auto\n")], r"robots: .*at least 2"),
    ("duplicate robots", [mission_edit("name: b", "name: a")], r"robot names must be unique"),
    ("reference maps itself", [mission_edit("mapper: b", "mapper: a")],
     r"plan\[0\]: robot 'a' cannot map around itself"),
    ("unknown world", [mission_edit("world: world.yaml", "world: atlantis")],
     r"'atlantis' is neither a world file nor a built-in world"),
    ("world path outside", [mission_edit("world: world.yaml", "world: ../../nowhere/w.yaml")],
     r"nowhere/w\.yaml: no such file"),
    ("FIFO", [fifo(MISSION)], r"mission\.yaml: not a regular file"),
    ("a directory", [directory(MISSION)], r"mission\.yaml: is a directory"),
    ("a list", [mission("- world\n")], r"mission\.yaml: expected a YAML mapping"),
    ("unknown key", [mission(GOOD_MISSION + "speed: 3\n")], r"speed: unknown key"),
    ("seed a word", [mission_edit("seed: 1", "seed: lucky")], r"seed: "),
    ("start NaN", [mission_edit("start: [2, 2, 90]", "start: [.nan, 2, 90]")],
     r"robots\[1\]\.start"),
    ("start of two numbers", [mission_edit("start: [2, 2, 90]", "start: [2, 2]")],
     r"robots\[1\]\.start"),
    ("empty plan", [mission(GOOD_MISSION.split("plan:")[0] + "plan: []\n")],
     r"plan has no steps"),
    ("plan neither auto nor steps", [mission(GOOD_MISSION.split("plan:")[0] + "plan: manual\n")],
     r"plan"),
    ("step without scans", [mission_edit("scans: [[3, 2, 0]]", "scans: []")],
     r"plan\.list\[StepSpec\]\[0\]\.scans: List should have at least 1 item"),
    ("start outside the world", [mission_edit("start: [2, 2, 90]", "start: [40, 2, 90]")],
     r"\(40, 2\)|outside|not in|free space"),
    ("scan pose outside the world", [mission_edit("[[3, 2, 0]]", "[[3, 99, 0]]")],
     r"\(3, 99\)|outside|not in|reach"),
    ("config with an unknown key", [mission(GOOD_MISSION + "config: {grid: {bogus: 1}}\n")],
     r"grid\.bogus: unknown key"),
    ("auto with 0 stations", [mission(GOOD_MISSION.split("plan:")[0] +
                                      "plan: auto\nauto: {stations: 0}\n")], r"auto\.stations"),
    ("an alias", [mission("s: &s [1, 1, 0]\n" + GOOD_MISSION.replace("[1, 1, 0]", "*s"))],
     r"aliases \(\*name\) are not allowed"),
    ("binary", [write(MISSION, b"\x00\x01\xff" * 40)], r"mission\.yaml: not UTF-8"),
    ("missing file", [remove(MISSION)], r"mission\.yaml: no such file"),
]  # fmt: skip

MISSION_CASES = [
    Case("sim-mission", f"simulate: {damage}", SIMULATE, error=pattern,
         setup=(GOOD_WORLD, *setups))
    for damage, setups, pattern in MISSION_DAMAGES
] + [
    Case("sim-mission", "simulate: unknown built-in mission", ("simulate", "atlantis", "--out",
         "{tmp}/ds"), error=r"'atlantis' is neither a mission file nor a built-in mission"),
    Case("sim-mission", "simulate: negative --seed", (*SIMULATE, "--seed", "-1"),
         setup=(GOOD_WORLD, mission(GOOD_MISSION)), error=r"seed must be >= 0, got -1"),
    Case("sim-mission", "simulate: negative seed in the mission", SIMULATE,
         setup=(GOOD_WORLD, mission_edit("seed: 1", "seed: -5")),
         error=r"mission\.yaml: seed: .*greater than or equal to 0"),
    Case("sim-mission", "lms emulate: pose outside the world", ("lms", "emulate", "--world", WORLD,
         "--pose", "40", "1", "0", "--seconds", "0.1"), setup=(GOOD_WORLD,),
         error=r"pose \(40, 1\) lies outside every room of w"),
    Case("sim-mission", "lms emulate: negative --seed", ("lms", "emulate", "--seed", "-1",
         "--seconds", "0.1"), error=r"--seed must be >= 0, got -1"),
    Case("sim-mission", "evaluate-localization: negative --seed", ("evaluate-localization",
         "--only", "sim", "--trials", "1", "--seed", "-2"), error=r"--seed must be >= 0, got -2"),
    Case("sim-mission", "lms emulate: NaN pose", ("lms", "emulate", "--world", WORLD, "--pose", "nan",
         "1", "0", "--seconds", "0.1"), setup=(GOOD_WORLD,), error=r"pose"),
]  # fmt: skip

CAP = "{tmp}/lms.cap"
DECODE = ("lms", "decode", CAP)
L = "lms-decode"


def damaged_capture(change: object) -> tuple[Setup, Setup]:
    return (_capture, edit(CAP, change))  # type: ignore[arg-type]


def _capture(ws: object) -> None:
    from sensors.lms200.capture import CaptureWriter
    from sensors.lms200.protocol.scan import encode_scan

    path = Path(CAP.format(**ws.fields()))  # type: ignore[attr-defined]
    with CaptureWriter(path, {"baud_rate": 38400}) as writer:
        for k in range(300):
            ranges = 2.0 + 0.5 * np.sin(np.linspace(0, 3, 101) + k / 30)
            writer.write(k * 0.06, encode_scan(ranges))


def _middle(size: int, random: bool) -> object:
    def change(data: bytes) -> bytes:
        at = len(data) // 2
        fill = np.random.default_rng(9).bytes(size) if random else bytes(size)
        return data[:at] + fill + data[at + size :]

    return change


def _dump(data: bytes) -> bytes:
    import struct

    pos = data.index(b"\n", data.index(b"\n") + 1) + 1
    out = bytearray()
    while pos < len(data):
        size = struct.unpack_from("<dI", data, pos)[1]
        out += data[pos + 12 : pos + 12 + size]
        pos += 12 + size
    return bytes(out)


DECODE_CASES = [
    Case(L, "intact", DECODE, setup=(_capture,), ok=r"300 telegrams \(300 scans.*0 checksum "
         r"failures, 0 undecodable, 0 implausible, 0 bytes skipped\n"),
    Case(L, "random bytes", DECODE, setup=(write(CAP, lambda: np.random.default_rng(8).bytes(
         100_000)),), ok=r"100,000 bytes, 0 telegrams .* [\d,]+ bytes skipped"),
    Case(L, "FIFO", DECODE, setup=(fifo(CAP),), error=r"lms\.cap: not a regular file"),
    Case(L, "a directory", DECODE, setup=(directory(CAP),), error=r"lms\.cap: is a directory"),
    Case(L, "missing", DECODE, error=r"lms\.cap: no such file"),
    Case(L, "empty", DECODE, setup=(write(CAP, b""),), ok=r"lms\.cap: 0 bytes, 0 telegrams"),
    Case(L, "truncated last record", DECODE, setup=damaged_capture(lambda b: b[:-50]),
         ok=r"299 telegrams .*, \d+ bytes truncated"),
    Case(L, "truncated header", DECODE, setup=damaged_capture(lambda b: b[:25]),
         error=r"lms\.cap: capture header line is truncated"),
    Case(L, "magic line only", DECODE, setup=damaged_capture(lambda b: b[:17]),
         error=r"lms\.cap: capture header line is truncated"),
    Case(L, "header not JSON", DECODE, setup=damaged_capture(
        lambda b: b[:17] + b"{oops\n" + b[b.index(b"\n", 17) + 1 :]),
        error=r"lms\.cap: capture header is not JSON"),
    Case(L, "header a JSON list", DECODE, setup=damaged_capture(
        lambda b: b[:17] + b"[]\n" + b[b.index(b"\n", 17) + 1 :]),
        error=r"lms\.cap: capture header is not a JSON object"),
    Case(L, "zeroed stretch in the middle", DECODE, setup=damaged_capture(_middle(2000, False)),
         ok=r"29\d telegrams .*, [\d,]+ bytes of damaged records lost"),
    Case(L, "random stretch in the middle", DECODE, setup=damaged_capture(_middle(2000, True)),
         ok=r"29\d telegrams .*, [\d,]+ bytes of damaged records lost"),
    Case(L, "a few bytes flipped inside a record", DECODE, setup=damaged_capture(
        lambda b: b[:-100] + bytes(x ^ 0xFF for x in b[-100:-90]) + b[-90:]),
         ok=r"299 telegrams .*[1-9] checksum failures"),
    Case(L, "a plain dump", DECODE, setup=damaged_capture(_dump), ok=r"300 telegrams"),
    Case(L, "a plain dump cut short", DECODE, setup=damaged_capture(lambda b: _dump(b)[:-30]),
         ok=r"299 telegrams"),
    Case(L, "--direction bogus", (*DECODE, "--direction", "up"), setup=(_capture,),
         error=r"direction"),
]  # fmt: skip

GUARDED = [
    Case(L, "/dev/zero", ("lms", "decode", "/dev/zero"), guarded=True,
         error=r"/dev/zero: not a regular file"),
    Case("world", "world-show: /dev/zero", ("world", "show", "/dev/zero", "--out", "{tmp}/w.png"),
         guarded=True, error=r"/dev/zero: not a regular file"),
    Case("sim-mission", "simulate: /dev/zero", ("simulate", "/dev/zero", "--out", "{tmp}/ds"),
         guarded=True, error=r"/dev/zero: not a regular file"),
]  # fmt: skip

CASES = WORLD_CASES + MISSION_CASES + DECODE_CASES


@pytest.fixture(scope="module")
def guarded(tmp_path_factory: pytest.TempPathFactory) -> Guarded:
    return run_guarded(GUARDED, tmp_path_factory.mktemp("guarded"), None)


@cases_param(CASES)
def test_a_damaged_world_mission_or_capture_is_one_line(case: Case, tmp_path: Path) -> None:
    execute(case, workspace(case, tmp_path, None))


@cases_param(GUARDED)
def test_a_device_as_world_mission_or_capture_is_refused(case: Case, guarded: Guarded) -> None:
    execute(case, guarded.workspaces[case.id], guarded.outcomes[case.id])


def test_the_intact_world_and_mission_simulate(tmp_path: Path) -> None:
    """The base of the damaged cases is valid: a damage is what they refuse."""
    from sensors.sim.mission import load_mission
    from sensors.sim.world import load_world

    ws = workspace(Case("world", "intact", ("x",), ok="."), tmp_path, None)
    GOOD_WORLD(ws)
    (tmp_path / "mission.yaml").write_text(GOOD_MISSION)
    assert load_world(tmp_path / "world.yaml").rooms[0].name == "r"
    assert load_mission(tmp_path / "mission.yaml").robot_names() == ["a", "b"]
