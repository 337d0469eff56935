"""Family 7: output safety. Every command with an output folder refuses, before any work, a
folder it did not write — a user's folder, the input dataset, a folder of datasets, a parent of
the dataset, a regular file, the working folder, a symbolic link, an output of another kind —
and leaves every byte of it as it was; an earlier output of its own kind is replaced.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.estimation.app.cli.malformed import (
    Case,
    Outcome,
    Setup,
    Workspace,
    cases_param,
    copy,
    execute,
    simulated_dataset,
    snapshot,
    symlink,
    workspace,
    write,
)

ROOM = (
    "name: w\nrooms:\n  - {name: r, footprint: [[0, 0], [6, 0], [6, 5], [0, 5]], ceiling_m: 2.6}\n"
)
MISSION = (
    "world: world.yaml\nseed: 1\nrobots:\n  - {name: a, start: [1, 1, 0]}\n"
    "  - {name: b, start: [2, 2, 90]}\nplan:\n  - {reference: a, mapper: b, scans: [[3, 2, 180]]}\n"
)
#: Each command with an output folder, the kind it writes, and its line with OUT for --out.
COMMANDS: dict[str, tuple[str, tuple[str, ...]]] = {
    "simulate": ("dataset", ("simulate", "{tmp}/mission.yaml", "--out", "OUT")),
    "demo": ("dataset", ("demo", "--out", "OUT")),
    "batch": ("result", ("batch", "{ds}", "--out", "OUT")),
    "isam": ("result", ("isam", "{ds}", "--out", "OUT")),
    "dataset-merge": (
        "dataset",
        ("dataset", "merge", "{tmp}/nothing", "--robot", "a=0,0,0", "--out", "OUT"),
    ),
    "record": (
        "recording",
        ("record", "--robot", "a", "--clock-offset", "0", "--seconds", "0.1", "--out", "OUT"),
    ),
}


def user_folder(rel: str) -> Setup:
    def setup(ws: Workspace) -> None:
        folder = ws.tmp / rel
        (folder / "sub").mkdir(parents=True)
        (folder / "notes.txt").write_text("my notes\n")
        (folder / "sub" / "data.bin").write_bytes(bytes(range(256)))

    return setup


def hidden_only(rel: str) -> Setup:
    def setup(ws: Workspace) -> None:
        (ws.tmp / rel).mkdir()
        (ws.tmp / rel / ".notes").write_text("hidden\n")

    return setup


def datasets_folder(ws: Workspace) -> None:
    folder = ws.tmp / "missions"
    folder.mkdir()
    for name in ("one", "two"):
        copy("{ds}", f"missions/{name}")(ws)


#: (damage, --out, setups, trees kept (relative to {tmp}), error pattern); kind-specific cases
#: are added per command below.
REFUSALS = [
    ("a folder holding a user's file", "{tmp}/mine", [user_folder("mine")], ("mine",),
     r"mine: holds files coopmap did not write \(notes\.txt, sub\)"),
    ("a folder holding only a hidden file", "{tmp}/mine", [hidden_only("mine")], ("mine",),
     r"mine: holds files coopmap did not write \(\.notes\)"),
    ("a folder holding several datasets", "{tmp}/missions", [datasets_folder], ("missions",),
     r"missions: holds files coopmap did not write \(one, two\)"),
    ("the parent of the dataset", "{tmp}", [], ("ds",),
     r"holds files coopmap did not write \(ds, mission\.yaml, world\.yaml\)", "{repo}"),
    ("an existing regular file", "{tmp}/notes.txt", [write("notes.txt", "keep me\n")],
     ("notes.txt",), r"notes\.txt: exists and is not a folder; refusing to replace it"),
    ("the working folder", ".", [user_folder("mine")], ("mine", "ds"),
     r"\.: refusing to write into the working folder or its parent"),
    ("the working folder's parent", "..", [], ("ds",),
     r"\.\.: refusing to write into the working folder or its parent"),
    ("the working folder by its path", "{tmp}", [], ("ds",),
     r"refusing to write into the working folder or its parent"),
    ("a symbolic link to a user's folder", "{tmp}/link", [user_folder("mine"),
     symlink("link", "{tmp}/mine")], ("mine", "link"),
     r"link: is a symbolic link; refusing to replace it"),
    ("a dangling symbolic link", "{tmp}/link", [symlink("link", "{tmp}/nowhere")], ("link",),
     r"link: is a symbolic link; refusing to replace it"),
    ("a folder of the dataset", "{ds}/robots", [], ("ds",),
     r"robots: holds files coopmap did not write \(a, b\)"),
]  # fmt: skip


def _refusal(command: str, damage: str, out: str, setups: list[Setup], keep: tuple[str, ...],
             pattern: str, cwd: str | None = None) -> Case:  # fmt: skip
    _, args = COMMANDS[command]
    line = tuple(out if a == "OUT" else a for a in args)
    base: list[Setup] = [write("mission.yaml", MISSION), write("world.yaml", ROOM)]
    return Case("output", f"{command}: {damage}", line, error=pattern,
                setup=(*base, *setups), keep=keep, cwd=cwd, dataset=True)  # fmt: skip


def _other_kind(command: str) -> Case:
    kind, _ = COMMANDS[command]
    if kind == "dataset":  # a result folder as a dataset's --out
        return _refusal(
            command,
            "an output of another kind",
            "{ds}/result",
            [],
            ("ds",),
            r"result: holds a coopmap result; refusing to replace it with a dataset",
        )
    if kind == "result":  # the dataset as a result's --out
        return _refusal(
            command,
            "the input dataset itself",
            "{ds}",
            [],
            ("ds",),
            r"holds a coopmap dataset; refusing to replace it with a result",
        )
    return _refusal(
        command,
        "an output of another kind",
        "{ds}",
        [],
        ("ds",),
        r"holds a coopmap dataset; refusing to replace it with a recording",
    )


CASES = [_refusal(command, *refusal) for command in COMMANDS for refusal in REFUSALS] + [
    _other_kind(command) for command in COMMANDS
]
CASES += [
    _refusal("simulate", "a robot's folder of the dataset", "{ds}/robots/a", [], ("ds",),
             r"robots/a: holds files coopmap did not write \(lms\.cap, odometry\.tum\)"),
    _refusal("batch", "a previous recording", "{tmp}/rec", [write("rec/.coopmap",
             '{"kind": "recording"}\n'), write("rec/odometry.log", "1 2 3\n")], ("rec",),
             r"rec: holds a coopmap recording; refusing to replace it with a result"),
]  # fmt: skip


def lms_record(damage: str, out: str, setups: list[Setup], keep: tuple[str, ...], error: str
               ) -> Case:  # fmt: skip
    return Case("output", f"lms-record: {damage}", ("lms", "record", "--port", "loop://", "--out",
                out, "--seconds", "0.1"), setup=tuple(setups), keep=keep, error=error)  # fmt: skip


CASES += [
    lms_record("an existing capture", "{tmp}/a.cap", [write("a.cap", b"COOPMAP-LMSCAP 1\n{}\n")],
               ("a.cap",), r"a\.cap: already exists; choose another name or remove it"),
    lms_record("a user's file", "{tmp}/notes.txt", [write("notes.txt", "mine\n")],
               ("notes.txt",), r"notes\.txt: already exists"),
    lms_record("a folder", "{tmp}/mine", [user_folder("mine")], ("mine",),
               r"mine: already exists"),
    lms_record("a symbolic link", "{tmp}/link", [write("mine.cap", "x"),
               symlink("link", "{tmp}/mine.cap")], ("mine.cap", "link"), r"link: already exists"),
    lms_record("a recording cut short", "{tmp}/b.cap", [write("b.cap.partial", "partial\n")],
               ("b.cap.partial",), r"b\.cap\.partial: a recording that was cut short is there"),
    Case("output", "world-show: --out a folder", ("world", "show", "essex_lab", "--out",
         "{tmp}/w.png"), setup=(user_folder("w.png"),), keep=("w.png",), error=r"w\.png"),
    Case("output", "world-generate: --out a folder", ("world", "generate", "--seed", "1",
         "--out", "{tmp}/g.yaml"), setup=(user_folder("g.yaml"),), keep=("g.yaml",),
         error=r"g\.yaml"),
    Case("output", "evaluate: --result a user's folder with a report", ("evaluate", "{ds}",
         "--result", "{tmp}/mine"), setup=(user_folder("mine"), copy("{ds}/result/report.json",
         "mine/report.json"), write("mine/metrics.json", "my metrics\n")), keep=("mine",),
         error=r"mine: not a coopmap result \(no \.coopmap marker of a result\)"),
    Case("output", "evaluate: --result a symbolic link", ("evaluate", "{ds}", "--result",
         "{tmp}/link"), setup=(symlink("link", "{ds}/result"),), keep=("ds", "link"),
         error=r"link: is a symbolic link"),
    Case("output", "evaluate: --result the dataset", ("evaluate", "{ds}", "--result", "{ds}"),
         keep=("ds",), error=r"no result here"),
]  # fmt: skip


def replaced(path: str, gone: str, fresh: str) -> object:
    """A check: the earlier output at ``path`` was replaced (``gone`` left with it, ``fresh``
    written anew), the other trees untouched, no hidden work folder left behind."""

    def check(ws: Workspace, outcome: Outcome) -> None:
        folder = Path(path.format(**ws.fields()))
        assert not (folder / gone).exists()
        assert (folder / fresh).is_file()
        assert [p.name for p in folder.parent.glob(f".{folder.name}.*") if p.is_dir()] == []

    return check


REPLACED = [
    Case("output", "simulate: an earlier dataset is replaced", ("simulate", "{tmp}/mission.yaml",
         "--out", "{tmp}/old"), setup=(write("mission.yaml", MISSION), write("world.yaml", ROOM),
         copy("{ds}", "old"), write("old/stale.txt", "from the earlier run\n")), dataset=True,
         ok=r"coopmap simulate: mission in w", check=replaced("{tmp}/old", "stale.txt",
         "mission.yaml"), keep=("ds",)),
    Case("output", "batch: an earlier result is replaced", ("batch", "{ds}", "--out",
         "{tmp}/old"), setup=(copy("{ds}/result", "old"), write("old/stale.txt", "x\n")),
         ok=r"coopmap batch: 14 sweeps", check=replaced("{tmp}/old", "stale.txt", "report.json")),
    Case("output", "isam: an earlier result is replaced", ("isam", "{ds}", "--out", "{tmp}/old"),
         setup=(copy("{ds}/result", "old"), write("old/stale.txt", "x\n")),
         ok=r"coopmap isam: \d+ events", check=replaced("{tmp}/old", "stale.txt", "report.json")),
    Case("output", "evaluate: an earlier metrics.json is replaced", ("evaluate", "{ds}"),
         setup=(write("{ds}/result/metrics.json", "stale\n"),), ok=r"map at 0\.1 m: precision",
         check=lambda ws, o: json.loads((ws.result / "metrics.json").read_text())["map"] or None),
]  # fmt: skip

ALL = CASES + REPLACED


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory, essex_simulated: Path) -> Path:
    return simulated_dataset(tmp_path_factory, essex_simulated)


@cases_param(CASES)
def test_an_output_that_is_not_coopmaps_is_refused_and_kept(
    case: Case, tmp_path: Path, dataset: Path
) -> None:
    ws = workspace(case, tmp_path, dataset)
    before = snapshot(ws.tmp)
    execute(case, ws)
    assert snapshot(ws.tmp) == before  # nothing at all was written, not even a hidden folder


@cases_param(REPLACED)
def test_an_earlier_output_of_the_same_kind_is_replaced(
    case: Case, tmp_path: Path, dataset: Path
) -> None:
    execute(case, workspace(case, tmp_path, dataset))


def test_every_command_with_an_output_folder_is_covered() -> None:
    covered = {c.id.split(":")[1].split("-", 1)[0] for c in ALL}
    assert {"simulate", "demo", "batch", "isam", "dataset", "record", "lms", "world",
            "evaluate"} <= covered  # fmt: skip
