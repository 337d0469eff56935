"""The command line: outputs, and one clear line with exit code 2 on every known error."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from estimation.app.config import Config
from tests.estimation.app.cli.clirun import assert_one_line_error, run

BUILTIN = ["essex_lab", "office_loop", "cluttered_hall"]
COOPMAP = Path(sys.executable).parent / "coopmap"


def read_png(path: Path) -> np.ndarray:
    from matplotlib.image import imread

    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    return np.asarray(imread(path))


@pytest.mark.parametrize("world", BUILTIN)
def test_world_show_draws_each_builtin_world(tmp_path: Path, world: str) -> None:
    out = tmp_path / f"{world}.png"
    code, stdout, stderr = run("world", "show", world, "--out", str(out))
    assert code == 0, stderr
    assert f"wrote {out}" in stdout
    image = read_png(out)
    height, width = image.shape[:2]
    assert width >= 600
    assert height >= 600
    assert 20_000 < out.stat().st_size < 2_000_000
    rgb = image[..., :3].reshape(-1, 3)
    # Not blank: many distinct colours, and plenty of non-white ink.
    assert len(np.unique((rgb * 255).astype(np.uint8), axis=0)) > 100
    assert (rgb.min(axis=1) < 0.9).mean() > 0.2


def test_world_show_reads_a_world_file(tmp_path: Path) -> None:
    world = tmp_path / "room.yaml"
    world.write_text(
        "name: room\nrooms:\n  - {name: r, footprint: [[0, 0], [5, 0], [5, 4], [0, 4]], ceiling_m: 2.6}\n"
        "boxes:\n  - {name: crate, center: [2, 2], size: [1, 1], z_m: [0, 1]}\n",
        encoding="utf-8",
    )
    out = tmp_path / "room.png"
    code, stdout, _ = run("world", "show", str(world), "--out", str(out))
    assert code == 0
    assert "room, 1 rooms, 1 boxes, 0 cylinders (0 movable)" in stdout
    assert read_png(out).shape[0] > 300


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ("rooms: [\n", r"bad\.yaml: malformed YAML at line 2"),
        ("name: w\nrooms:\n  - {name: r, footprint: [[0, 0], [0, 3], [4, 3], [4, 0]], ceiling_m: 2.5}\n",
         r"bad\.yaml: rooms\[0\]: room 'r': footprint is clockwise"),
        ("name: w\nrooms:\n  - {name: r, footprint: [[0, 0], [4, 0], [4, 3], [0, 3]], ceiling_m: 2.5}\n"
         "boxes:\n  - {name: b, center: [9, 9], size: [1, 1], z_m: [0, 1]}\n",
         r"bad\.yaml: boxes\[0\] 'b': centre \(9, 9\) lies outside every room"),
    ],
)  # fmt: skip
def test_world_show_bad_yaml_is_one_line(tmp_path: Path, text: str, pattern: str) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(text, encoding="utf-8")
    out = tmp_path / "out.png"
    assert_one_line_error(*run("world", "show", str(bad), "--out", str(out)), pattern)
    assert not out.exists()


def test_world_show_bad_paths_are_one_line(tmp_path: Path) -> None:
    assert_one_line_error(
        *run("world", "show", "no_such_world", "--out", str(tmp_path / "x.png")),
        r"'no_such_world' is neither a world file nor a built-in world \(built-in: "
        r"cluttered_hall, essex_lab, office_loop\)",
    )
    assert_one_line_error(
        *run("world", "show", str(tmp_path / "absent.yaml"), "--out", str(tmp_path / "x.png")),
        r"absent\.yaml: no such file",
    )
    assert_one_line_error(
        *run("world", "show", "essex_lab", "--out", str(tmp_path / "x.jpg")),
        r"x\.jpg: --out must name a \.png file",
    )
    blocker = tmp_path / "file"
    blocker.write_text("not a folder", encoding="utf-8")
    assert_one_line_error(
        *run("world", "show", "essex_lab", "--out", str(blocker / "x.png")), r"file"
    )


def test_world_show_keeps_the_old_figure_on_failure(tmp_path: Path) -> None:
    out = tmp_path / "keep.png"
    out.write_bytes(b"old figure")
    code, _, _ = run("world", "show", str(tmp_path / "absent.yaml"), "--out", str(out))
    assert code == 2
    assert out.read_bytes() == b"old figure"


def test_bad_config_is_one_line(tmp_path: Path) -> None:
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("grid: {resolution_m: -0.1}\n", encoding="utf-8")
    assert_one_line_error(
        *run("world", "show", "essex_lab", "--out", str(tmp_path / "x.png"), "--config", str(cfg)),
        r"cfg\.yaml: grid\.resolution_m: Input should be greater than or equal to 0\.005 \(got -0\.1\)",
    )
    assert_one_line_error(
        *run("demo", "--out", str(tmp_path / "d"), "--config", str(tmp_path / "none.yaml")),
        r"none\.yaml: no such file",
    )


def test_config_show_prints_the_effective_config(tmp_path: Path) -> None:
    code, stdout, _ = run("config", "show")
    assert code == 0
    assert yaml.safe_load(stdout) == Config().model_dump(mode="json")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("grid: {resolution_m: 0.05}\n", encoding="utf-8")
    code, stdout, _ = run("config", "show", "--config", str(cfg))
    shown = yaml.safe_load(stdout)
    assert shown["grid"]["resolution_m"] == 0.05
    assert shown["grid"]["prob_hit"] == 0.7


def test_world_list_names_the_builtins() -> None:
    code, stdout, _ = run("world", "list")
    assert code == 0
    assert [line.split()[0] for line in stdout.strip().splitlines()] == sorted(BUILTIN)


def test_demo_runs_the_default_mission(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    code, stdout, stderr = run("demo", "--out", str(out))
    assert code == 0, stderr
    for name in ("events.jsonl", "robots/a/lms.cap", "result/poses/a.tum", "result/map.npz",
                 "result/map.ply", "result/ceiling.pgm", "result/ceiling.yaml", "result/graph.g2o",
                 "result/report.md", "result/metrics.json", "result/config.yaml",
                 "result/figures/ceiling_trajectories.png", "result/figures/map_cubes.png",
                 "result/view/world_top.png", "result/view/view.ply"):  # fmt: skip
        assert (out / name).is_file(), name
    assert "coopmap demo: essex_lab, 2 robots" in stdout
    metrics = json.loads((out / "result" / "metrics.json").read_text())
    for robot in ("a", "b"):
        assert metrics["robots"][robot]["ate_m"] < 0.05
        assert metrics["robots"][robot]["ate_deg"] < 0.5
    assert metrics["map"]["precision"] > 0.9
    assert metrics["map"]["recall"] > 0.9


@pytest.mark.skipif(not COOPMAP.exists(), reason="console script not installed beside python")
def test_console_script_errors_without_traceback(tmp_path: Path) -> None:
    proc = subprocess.run(
        [
            str(COOPMAP),
            "world",
            "show",
            str(tmp_path / "nope.yaml"),
            "--out",
            str(tmp_path / "x.png"),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"coopmap: error: {tmp_path / 'nope.yaml'}: no such file"
    assert proc.stdout == ""


def test_a_robot_left_without_poses_fails_the_run_in_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    import typer

    from estimation.app.cli.mission import fail_unplaced

    with pytest.raises(typer.Exit) as info:
        fail_unplaced(
            {"robots": {"a": {"poses": 3}, "c": {"poses": 0}, "d": {"poses": 0}}}, tmp_path
        )
    assert info.value.exit_code == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "coopmap: error: robots c, d have no pose in the result: no mutual observation tied them "
        f"to the map (see unseen_pairs and missing_sweeps in {tmp_path / 'report.json'})"
    ]
    with pytest.raises(typer.Exit):
        fail_unplaced({"robots": {"a": {"poses": 3}, "c": {"poses": 0}}}, tmp_path)
    assert capsys.readouterr().err.startswith("coopmap: error: robot c has no pose")
    fail_unplaced({"robots": {"a": {"poses": 3}}}, tmp_path)
    assert capsys.readouterr().err == ""


def test_evaluate_prints_relocalization_after_the_changes(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """The relocalization verdicts were only in metrics.json; evaluate prints them per band."""
    metrics = {
        "robots": {"a": {"poses": 3, "ate_m": 0.01, "ate_deg": 0.1}},
        "mutual": {"events": 2, "rejected": 0, "median_m": None},
        "map": {"resolution_m": 0.1, "precision": 0.99, "recall": 0.9, "occupied": 100},
        "global_localization": {
            "relocalization_ceiling": {"searches": 2, "success": 2, "median_m": 0.033,
                                       "median_deg": 0.38},
            "relocalization_floor": {"searches": 2, "success": 1, "median_m": 0.107,
                                     "median_deg": 0.25},
        },
    }  # fmt: skip
    monkeypatch.setattr("estimation.app.evaluation.evaluate.evaluate", lambda *_: metrics)
    code, out, err = run("evaluate", str(tmp_path))
    assert code == 0, err
    lines = out.splitlines()
    assert "relocalization (ceiling band): 2 of 2 within 10 cm and 1°, median error 3.3 cm / " \
        "0.38°" in lines  # fmt: skip
    assert "relocalization (floor band): 1 of 2 within 10 cm and 1°, median error 10.7 cm / " \
        "0.25°" in lines  # fmt: skip


@pytest.mark.parametrize("command", ["batch", "isam"])
@pytest.mark.parametrize(("flag", "drawn"), [([], True), (["--figures"], True),
                                             (["--no-figures"], False)])  # fmt: skip
def test_batch_and_isam_pass_the_figures_choice_on(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, command: str, flag: list[str], drawn: bool
) -> None:
    asked: list[bool] = []

    class StopError(Exception):
        """The stand-in's way to end the command once it has seen the choice."""

    def runner(*_: object, figures: bool, **__: object) -> None:
        asked.append(figures)
        raise StopError

    monkeypatch.setattr(f"estimation.app.pipeline.run_{command}", runner)
    code, _, _ = run(command, str(tmp_path), *flag)
    assert code != 0  # the stand-in stops the run
    assert asked == [drawn]
