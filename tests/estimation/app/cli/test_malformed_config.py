"""Family 1: a malformed ``--config`` file given to every command that takes one.

Each command must refuse it with one line naming the file (or the key), before any work: no
traceback, no hang on a FIFO, no memory filled by an alias bomb or a device.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.estimation.app.cli.malformed import (
    Case,
    Guarded,
    cases_param,
    directory,
    execute,
    fifo,
    remove,
    run_guarded,
    symlink,
    workspace,
    write,
)

CFG = "{tmp}/cfg.yaml"

#: Every command that takes --config, with arguments that are valid enough that only the
#: configuration can be wrong (a run the configuration lets through ends quickly: --seconds,
#: --repeats, an absent --data).
COMMANDS: dict[str, tuple[str, ...]] = {
    "simulate": ("simulate", "essex_lab", "--out", "{tmp}/sim"),
    "batch": ("batch", "{ds}"),
    "isam": ("isam", "{ds}"),
    "demo": ("demo", "--out", "{tmp}/demo"),
    "localize": ("localize", "--map", "{tmp}/map.yaml", "--scan", "{tmp}/scan.yaml"),
    "evaluate-localization": ("evaluate-localization", "--only", "sim", "--trials", "1"),
    "evaluate-missions": ("evaluate-missions", "--worlds", "1", "--seed", "0", "--out", "{tmp}/em"),
    "world-show": ("world", "show", "essex_lab", "--out", "{tmp}/w.png"),
    "world-list": ("world", "list"),
    "config-show": ("config", "show"),
    "bench-fusion": (
        "bench",
        "fusion",
        "--repeats",
        "1",
        "--refusion-scans",
        "0",
        "--data",
        "{tmp}/nodata",
    ),
    "bench-scan": ("bench", "scan"),
    "bench-decode": ("bench", "decode", "--telegrams", "100", "--repeats", "1"),
    "bench-search": ("bench", "search", "--repeats", "1"),
    "bench-graph": ("bench", "graph", "--case", "leapfrog_5000", "--data", "{tmp}/nodata"),
    "lms-decode": ("lms", "decode", "{tmp}/none.cap"),
    "lms-emulate": ("lms", "emulate", "--seconds", "0.1"),
    "lms-record": (
        "lms",
        "record",
        "--port",
        "loop://",
        "--out",
        "{tmp}/r.cap",
        "--seconds",
        "0.1",
    ),
    "record": ("record", "--robot", "a", "--out", "{tmp}/rec", "--seconds", "0.1"),
    "replay": ("replay", "{tmp}/nodataset", "--robot", "a"),
    "dataset-merge": ("dataset", "merge", "{tmp}/nothing", "--out", "{tmp}/merged"),
    "world-generate": ("world", "generate", "--seed", "1", "--out", "{tmp}/gen.yaml"),
    "import": ("import", "{tmp}/none.mcap", "--out", "{tmp}/imported"),
    "robot": ("robot", "essex_lab", "--name", "a", "--simulate", "--dir", "{tmp}/robot"),
    "base": ("base", "essex_lab", "--out", "{tmp}/base", "--join-timeout", "1"),
    "live": ("live", "essex_lab", "--out", "{tmp}/live"),
}


def _alias_bomb() -> str:
    lines = ["a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for n in range(1, 12):
        prev = chr(ord("a") + n - 1)
        here = chr(ord("a") + n)
        lines.append(f"{here}: &{here} [{', '.join(['*' + prev] * 10)}]")
    return "\n".join(lines) + "\n"


def _sparse(size: int):  # a file that declares its size without taking the disk
    def setup(ws) -> None:  # type: ignore[no-untyped-def]
        path = ws.tmp / "cfg.yaml"
        with path.open("wb") as handle:
            handle.truncate(size)

    return setup


#: (damage, setups, error pattern, bomb)
DAMAGES = [
    ("malformed YAML", [write(CFG, "grid: [0.1,\n  prob_hit: }\n")], r"cfg\.yaml: malformed YAML",
     False),
    ("alias bomb", [write(CFG, _alias_bomb())], r"aliases \(\*name\) are not allowed", True),
    ("nesting 20000 deep", [write(CFG, "a: " + "[" * 20000 + "]" * 20000 + "\n")],
     r"cfg\.yaml: malformed YAML at line 1, column \d+: nested more than 100 levels", True),
    ("a FIFO", [fifo(CFG)], r"cfg\.yaml: not a regular file", False),
    ("a directory", [directory(CFG)], r"cfg\.yaml: is a directory", False),
    ("a missing file", [remove(CFG)], r"cfg\.yaml: no such file", False),
    ("binary bytes", [write(CFG, bytes(range(256)) * 4)], r"cfg\.yaml: not UTF-8", False),
    ("a list at the top level", [write(CFG, "- grid\n- search\n")],
     r"expected a YAML mapping at the top level, got list", False),
    ("a scalar at the top level", [write(CFG, "42\n")],
     r"expected a YAML mapping at the top level, got int", False),
    ("an unknown key", [write(CFG, "grid:\n  resolutoin_m: 0.1\n")],
     r"grid\.resolutoin_m: unknown key", False),
    ("an unknown section", [write(CFG, "gird:\n  resolution_m: 0.1\n")],
     r"gird: unknown key", False),
    ("an out-of-range value", [write(CFG, "grid:\n  prob_hit: 1.5\n")],
     r"grid\.prob_hit: .*less than 1", False),
    ("a NaN value", [write(CFG, "search:\n  beta: .nan\n")], r"search\.beta: .*finite", False),
    ("an infinite value", [write(CFG, "mirror:\n  period_s: .inf\n")],
     r"mirror\.period_s: .*finite", False),
    ("grid resolution 0.0005", [write(CFG, "grid:\n  resolution_m: 0.0005\n")],
     r"grid\.resolution_m: .*greater than or equal to 0\.005", False),
    ("a mistyped value", [write(CFG, "grid:\n  resolution_m: fine\n")],
     r"grid\.resolution_m: .*(number|float)", False),
    ("a section that is not a mapping", [write(CFG, "grid: 5\n")], r"grid: ", False),
    ("a very large file", [_sparse(64 * 2**20)], r"cfg\.yaml: 67,108,864 bytes, more than", True),
]  # fmt: skip

#: Damages of the values, not of the file: ``dataset merge`` validates its configuration only
#: with the merged dataset, after reading every recording (estimation/app/merge.py).
VALUES = {"an unknown key", "an unknown section", "an out-of-range value", "a NaN value",
          "an infinite value", "grid resolution 0.0005", "a mistyped value",
          "a section that is not a mapping"}  # fmt: skip

CASES = [
    Case("config", f"{command}: {damage}", (*args, "--config", CFG), error=pattern,
         setup=tuple(setups), bomb=bomb and command == "config-show")
    for command, args in COMMANDS.items()
    for damage, setups, pattern, bomb in DAMAGES
    if not (command == "dataset-merge" and damage in VALUES)
]  # fmt: skip

#: Devices: read whole they would fill memory, so they run in a guarded subprocess.
GUARDED = [
    Case("config", f"{command}: /dev/zero", (*args, "--config", CFG),
         error=r"cfg\.yaml: not a regular file", setup=(symlink(CFG, "/dev/zero"),),
         guarded=True)
    for command, args in COMMANDS.items()
] + [
    Case("config", "config-show: /dev/zero named directly", ("config", "show", "-c", "/dev/zero"),
         error=r"/dev/zero: not a regular file", guarded=True),
    Case("config", "config-show: /dev/stdin", ("config", "show", "-c", "/dev/stdin"),
         error=r"/dev/stdin: not a regular file", guarded=True),
]  # fmt: skip

ACCEPTED = [
    Case("config", "config-show: an empty file", ("config", "show", "-c", CFG),
         ok=r"resolution_m: 0\.1\b", setup=(write(CFG, ""),)),
    Case("config", "config-show: a comment only", ("config", "show", "-c", CFG),
         ok=r"resolution_m: 0\.1\b", setup=(write(CFG, "# nothing here\n"),)),
    Case("config", "config-show: a valid override", ("config", "show", "-c", CFG),
         ok=r"resolution_m: 0\.2\b", setup=(write(CFG, "grid:\n  resolution_m: 0.2\n"),)),
    Case("config", "config-show: resolution at its 5 mm floor", ("config", "show", "-c", CFG),
         ok=r"resolution_m: 0\.005\b", setup=(write(CFG, "grid:\n  resolution_m: 0.005\n"),)),
    Case("config", "world-list: a valid override", ("world", "list", "-c", CFG),
         ok=r"essex_lab", setup=(write(CFG, "grid:\n  resolution_m: 0.2\n"),)),
]  # fmt: skip

ALL = CASES + GUARDED + ACCEPTED


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A dataset's mission and event log only: batch and isam validate the configuration when
    they read the mission, before any capture (a configuration let through fails on the
    missing captures instead, and the case with it)."""
    folder = tmp_path_factory.mktemp("mission") / "ds"
    folder.mkdir()
    (folder / "mission.yaml").write_text(
        "robots:\n- {name: a, start: [0, 0, 0]}\n- {name: b, start: [1, 0, 0]}\n"
    )
    (folder / "events.jsonl").write_text(
        '{"t_s": 0, "event": "dwell", "end_s": 31, "poses": {"a": 0, "b": 0}}\n'
    )
    return folder


@pytest.fixture(scope="module")
def guarded(tmp_path_factory: pytest.TempPathFactory, dataset: Path) -> Guarded:
    return run_guarded(GUARDED, tmp_path_factory.mktemp("guarded"), dataset)


@cases_param(CASES + ACCEPTED)
def test_a_malformed_config_is_one_line(case: Case, tmp_path: Path, dataset: Path) -> None:
    execute(case, workspace(case, tmp_path, dataset))


@cases_param(GUARDED)
def test_a_device_as_config_is_refused_unread(case: Case, guarded: Guarded) -> None:
    execute(case, guarded.workspaces[case.id], guarded.outcomes[case.id])


def test_every_command_with_a_config_option_is_covered() -> None:
    import typer.main

    from estimation.app.cli.main import app

    def walk(group: object, prefix: str) -> list[str]:
        names = []
        for name, command in getattr(group, "commands", {}).items():
            full = f"{prefix}{name}"
            if hasattr(command, "commands"):
                names += walk(command, f"{full}-")
            elif any("--config" in p.opts for p in command.params):
                names.append(full)
        return names

    found = set(walk(typer.main.get_command(app), ""))
    others = {n for n in found if n.startswith("calibrate")}  # its owners test it
    assert found - others == set(COMMANDS)
    assert len(ALL) >= 18 * len(DAMAGES)
