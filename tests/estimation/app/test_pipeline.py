"""The batch pipeline and the evaluation on a small simulated mission, and their bad inputs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from estimation.app.cli.main import app
from estimation.app.config import ConfigError
from estimation.app.dataset import load_dataset
from estimation.app.evaluation.evaluate import evaluate
from estimation.app.pipeline import run_batch
from estimation.app.sim.simulate import run_simulation
from mapping.formats.npz import load_map
from sensors.errors import SensorError
from sensors.trajio import read_g2o, read_tum
from tests.estimation.app.missions import copy_of
from tests.paths import REPO


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory, essex_simulated: Path) -> Path:
    return copy_of(essex_simulated, tmp_path_factory, "mission")


@pytest.fixture(scope="module")
def result(dataset: Path) -> Path:
    run_batch(dataset)
    return dataset / "result"


def test_batch_writes_the_result_directory(result: Path) -> None:
    report = json.loads((result / "report.json").read_text())
    assert report["observations"] >= 4
    assert report["missing_sweeps"] == []
    assert report["robots"]["a"]["checksum_failures"] == 0
    assert [r["implausible_scans"] for r in report["robots"].values()] == [0, 0]  # clean captures
    stamps, poses = read_tum(result / "poses" / "a.tum")
    assert stamps[0] == 0.5  # the first odometry sample half a second into the standstill
    np.testing.assert_allclose(poses[0], [2.0, 3.5, np.radians(20)], atol=1e-3)  # the gauge
    graph = read_g2o(result / "graph.g2o")
    assert graph.num_poses == sum(r["poses"] for r in report["robots"].values())
    assert len(graph.fixed) == 1
    grid = load_map(result / "map.npz")
    assert grid.known_count() > 100_000
    assert (result / "ceiling.pgm").read_bytes()[:2] == b"P5"
    assert "| robot | poses |" in (result / "report.md").read_text()


def test_report_json_is_the_report_the_run_returned(dataset: Path, tmp_path: Path) -> None:
    output = run_batch(dataset, tmp_path / "again", figures=False)
    written = json.loads((tmp_path / "again" / "report.json").read_text())
    assert written == json.loads(json.dumps(output.report, default=float))
    timings = written["timings_s"]
    steps = ["decode", "sweeps_and_beacons", "optimize", "search", "fusion"]
    assert list(timings) == [*steps, "total"]
    assert timings["total"] == pytest.approx(sum(timings[s] for s in steps))
    assert all(timings[s] >= 0.0 for s in steps)


def test_batch_refuses_to_write_over_its_dataset_or_a_folder_of_datasets(
    dataset: Path, tmp_path: Path
) -> None:
    from sensors.errors import OutputError

    before = sorted(p.name for p in dataset.iterdir())
    with pytest.raises(OutputError, match="holds a coopmap dataset; refusing to replace it"):
        run_batch(dataset, dataset)
    with pytest.raises(OutputError, match="holds files coopmap did not write"):
        run_batch(dataset, dataset.parent)
    assert sorted(p.name for p in dataset.iterdir()) == before


def test_timings_total_every_step() -> None:
    from estimation.app.pipeline import Timings

    assert Timings(1.0, 2.0, 3.0, 4.0, 5.0).as_json()["total"] == pytest.approx(15.0)
    assert Timings().as_json() == {
        "decode": 0.0, "sweeps_and_beacons": 0.0, "optimize": 0.0, "search": 0.0, "fusion": 0.0,
        "total": 0.0,
    }  # fmt: skip


def test_stations_hold_their_dwells_sweeps_in_time_order(dataset: Path) -> None:
    from estimation.app.dataset import load_dataset, stations
    from estimation.app.pipeline import prepare

    prepared = prepare(dataset, None, None)
    data = load_dataset(dataset)
    found = stations(data, prepared.sweeps)
    # a stands as the reference first; b then stands where it made its last mapper scan
    assert [s.label for s in found] == ["a0", "b3"]
    referenced = {f"{e['reference']}{e['poses'][e['reference']]}" for e in data.events
                  if e["event"] == "dwell" and e.get("reference")}  # fmt: skip
    assert {s.label for s in found} == referenced
    assert [s.time_s for s in found] == sorted(s.time_s for s in found)
    for station in found:
        assert {v.robot for v in station.views} == {"a", "b"}
        assert all(v.points_scanner.shape[1] == 3 for v in station.views)


def test_evaluation_meets_the_targets(dataset: Path, result: Path) -> None:
    metrics = evaluate(dataset)
    for robot in ("a", "b"):
        assert metrics["robots"][robot]["ate_m"] < 0.05
        assert metrics["robots"][robot]["ate_deg"] < 0.5
    assert metrics["mutual"]["median_m"] < 0.02
    assert metrics["map"]["precision"] >= 0.9
    assert metrics["map"]["recall"] >= 0.9
    coverage = metrics["coverage"]  # two leapfrog steps in one lab: part of its floor
    assert coverage["rooms"] == coverage["rooms_entered"] == ["lab"]
    assert 0.5 < coverage["coverage"] < 0.8
    assert json.loads((result / "metrics.json").read_text()) == json.loads(json.dumps(metrics))


def test_robots_decoded_beside_a_worker_are_the_robots_decoded_here(
    dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from estimation.app import pipeline
    from estimation.app.pipeline import prepare

    alone = prepare(dataset, None, None)
    monkeypatch.setattr(pipeline, "DECODE_WORKER_BYTES", 0)  # a worker for any capture
    beside = prepare(dataset, None, None)
    assert [(s.robot, s.index, s.dwell) for s in beside.sweeps] == [
        (s.robot, s.index, s.dwell) for s in alone.sweeps
    ]
    for a, b in zip(alone.sweeps, beside.sweeps, strict=True):
        np.testing.assert_array_equal(a.points_scanner, b.points_scanner)
        assert [d.center_scanner.tolist() for d in a.detections] == [
            d.center_scanner.tolist() for d in b.detections
        ]
    assert beside.counts == alone.counts
    assert sum(len(s.detections) for s in alone.sweeps) > 0
    assert {r: s.telegrams for r, s in beside.streams.items()} == {
        r: s.telegrams for r, s in alone.streams.items()
    }
    # A capture that fails in the worker (the last robot's: the worker takes from the back)
    # fails the run with the error it fails with here.
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy, ignore=shutil.ignore_patterns("result"))
    capture = copy / "robots" / "b" / "lms.cap"
    data = capture.read_bytes()
    capture.write_bytes(data[: data.index(b"\n", data.index(b"\n") + 1) + 1])  # no records
    with pytest.raises(SensorError, match="no measured values in the capture"):
        prepare(copy, None, None)
    monkeypatch.setattr(pipeline, "DECODE_WORKER_BYTES", 2**62)
    with pytest.raises(SensorError, match="no measured values in the capture"):
        prepare(copy, None, None)


def test_the_event_stream_takes_the_beacons_found_as_the_sweeps_were_made(
    dataset: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from estimation.app import events
    from estimation.app.pipeline import prepare

    alone = prepare(dataset, None, None)

    def refused(*args: object, **kwargs: object) -> None:
        raise AssertionError("the event stream looked for beacons again")

    monkeypatch.setattr(events, "detect_beacons", refused)
    again = prepare(dataset, None, None)
    assert [len(s.detections) for s in again.sweeps] == [len(s.detections) for s in alone.sweeps]
    assert again.counts == alone.counts


def test_garbage_in_a_capture_is_counted_not_fatal(dataset: Path, tmp_path: Path) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy, ignore=shutil.ignore_patterns("result"))
    capture = copy / "robots" / "b" / "lms.cap"
    data = bytearray(capture.read_bytes())
    rng = np.random.default_rng(0)
    start = len(data) // 2
    data[start : start + 3000] = rng.integers(0, 256, 3000, dtype=np.uint8).tobytes()
    capture.write_bytes(bytes(data))
    output = run_batch(copy, figures=False)
    assert output.report["robots"]["b"]["bytes_skipped"] > 0
    assert output.report["observations"] >= 3


def test_bad_datasets_are_clear_errors(dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not a coopmap dataset"):
        load_dataset(tmp_path)
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy, ignore=shutil.ignore_patterns("result"))
    (copy / "robots" / "a" / "lms.cap").unlink()
    with pytest.raises(SensorError, match=r"lms\.cap: no such file"):
        run_batch(copy)
    (copy / "events.jsonl").write_text('{"event": "dwell"}\n')
    with pytest.raises(ConfigError, match=r"events\.jsonl:1: an event needs 'event' and 't_s'"):
        load_dataset(copy)
    result = CliRunner().invoke(app, ["batch", str(tmp_path / "nothing")])
    assert result.exit_code == 2
    assert "not a coopmap dataset" in result.stderr
    result = CliRunner().invoke(app, ["evaluate", str(copy)])
    assert result.exit_code == 2
    assert "no result here" in result.stderr


MOVE = '{"t_s": 5, "event": "move", "robot": "b", "from_index": 0, "to_index": 1, "start_s": 1}'
DWELL = '{"t_s": 5, "event": "dwell", "end_s": 9, "poses": {"a": 0, "b": 1}}'


@pytest.mark.parametrize(
    ("line", "message"),
    [
        (DWELL.replace(', "end_s": 9', ""), r"dwell: end_s must be a number >= t_s"),
        (DWELL.replace('"t_s": 5', '"t_s": "soon"'), r"t_s must be a finite number, got 'soon'"),
        (DWELL.replace('"t_s": 5', '"t_s": NaN'), r"t_s must be a finite number, got nan"),
        (DWELL.replace(', "b": 1', ""), r"poses must give the pose index of every robot \(a, b\)"),
        (DWELL.replace('"b": 1', '"b": -1'), r"poses\.b must be an index >= 0"),
        (DWELL.replace("}}", '}, "reference": "z"}'), r"reference 'z' is not one of the mission"),
        (MOVE.replace('"robot": "b"', '"robot": "../../x"'), r"move of robot '\.\./\.\./x'"),
        (MOVE.replace('"to_index": 1', '"to_index": 3'), r"to_index must be from_index \+ 1"),
        (MOVE.replace(', "start_s": 1', ""), r"start_s must be a number <= t_s"),
        (MOVE.replace('"from_index": 0', '"from_index": "0"'), r"from_index must be an index"),
    ],
)
def test_malformed_events_are_named_with_their_line(
    dataset: Path, tmp_path: Path, line: str, message: str
) -> None:
    copy = tmp_path / "copy"
    copy.mkdir()
    shutil.copy(dataset / "mission.yaml", copy / "mission.yaml")
    (copy / "events.jsonl").write_text(MOVE + "\n" + line + "\n")
    with pytest.raises(ConfigError, match=r"events\.jsonl:2: (move: |dwell: )?" + message):
        load_dataset(copy)
    result = CliRunner().invoke(app, ["batch", str(copy)])
    assert result.exit_code == 2
    assert "Traceback" not in result.output


@pytest.mark.parametrize(
    ("robots", "message"),
    [
        ("[{name: ../../x, start: [0, 0, 0]}]", r"robots\[0\]: name must be one lowercase letter"),
        ("[{name: a, start: [0, 0, 0]}, {name: a, start: [1, 0, 0]}]", "listed twice"),
        ("[{name: a, start: [0, .nan, 0]}]", r"start must be \[x_m, y_m, yaw_deg\]"),
        ("[{name: a}]", r"start must be \[x_m, y_m, yaw_deg\], got None"),
        ("{a: 1}", "robots: must be a list"),
    ],
)
def test_malformed_robots_are_clear_errors(tmp_path: Path, robots: str, message: str) -> None:
    (tmp_path / "mission.yaml").write_text(f"robots: {robots}\n")
    (tmp_path / "events.jsonl").write_text("")
    with pytest.raises(ConfigError, match=message):
        load_dataset(tmp_path)


def test_a_dataset_without_sweeps_is_an_error(dataset: Path, tmp_path: Path) -> None:
    from estimation.errors import EstimationError

    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy, ignore=shutil.ignore_patterns("result*"))
    events = [json.loads(line) for line in (copy / "events.jsonl").read_text().splitlines()]
    kept = [e for e in events if e["event"] != "dwell"]
    (copy / "events.jsonl").write_text("".join(json.dumps(e) + "\n" for e in kept))
    with pytest.raises(EstimationError, match="no sweep in any dwell"):
        run_batch(copy)
    assert not (copy / "result").exists()


def test_failed_batch_keeps_the_earlier_result(dataset: Path, result: Path, tmp_path: Path) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    before = (copy / "result" / "report.json").read_text()
    (copy / "robots" / "b" / "lms.cap").write_bytes(b"COOPMAP-LMSCAP 1\n{}\n")
    with pytest.raises(SensorError, match="no measured values"):
        run_batch(copy)
    assert (copy / "result" / "report.json").read_text() == before


def test_isam_matches_batch_and_resumes_after_a_kill(
    dataset: Path, result: Path, tmp_path: Path
) -> None:
    from estimation.app.pipeline import run_isam

    whole = run_isam(dataset, tmp_path / "isam", figures=False)
    assert whole is not None
    batch_poses = {r: np.loadtxt(result / "poses" / f"{r}.tum", ndmin=2) for r in ("a", "b")}
    for robot, poses in whole.poses.items():
        for k, (index, pose) in enumerate(sorted(poses.items())):
            del index
            # the same factors (the searches ran on the same batch optimum): iSAM2's solution
            # and batch's agree to solver tolerance, far inside the 1 cm / 0.1°
            np.testing.assert_allclose(pose[:2], batch_poses[robot][k, 1:3], atol=1e-4)
    assert run_isam(dataset, tmp_path / "cut", stop_after=6) is None  # killed after 6 events
    assert (tmp_path / ".cut.checkpoint.npz").is_file()
    resumed = run_isam(dataset, tmp_path / "cut", resume=True, figures=False)
    assert resumed is not None
    assert resumed.report["isam2"]["events"] == whole.report["isam2"]["events"]
    for robot, poses in whole.poses.items():
        for index, pose in poses.items():
            # Both runs search on the batch optimum of the same events and settle iSAM2 (every
            # variable relinearized) at the end, so they end at the same optimum (within 1 µm:
            # floating-point noise in the solves).
            np.testing.assert_allclose(resumed.poses[robot][index], pose, atol=1e-6)
    assert not (tmp_path / ".cut.checkpoint.npz").exists()
    with pytest.raises(Exception, match="no checkpoint to resume from"):
        run_isam(dataset, tmp_path / "never", resume=True)


def test_isam_leaves_out_what_the_batch_optimum_dropped(
    dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """iSAM2 cannot tell an outlier: the factors the batch optimum after the searches dropped
    stay out of its settled estimate and are reported as outliers, as batch reports them."""
    from estimation.app import pipeline
    from estimation.posegraph.keys import pose_key
    from estimation.posegraph.smoother import BatchResult

    real = pipeline.optimize_batch
    dropped: list[str] = []
    optimum: dict[int, np.ndarray] = {}

    def dropping(factors, initial, robust="gnc_tls"):  # type: ignore[no-untyped-def]
        """The real optimum without the last mutual observation, which it marks dropped."""
        last = max(i for i, f in enumerate(factors) if f.kind == "mutual")
        kept = real([f for i, f in enumerate(factors) if i != last], initial, robust=robust)
        inliers = np.insert(kept.inliers, last, False)
        dropped[:] = [factors[last].describe()]
        optimum.update(kept.estimate)
        return BatchResult(kept.estimate, inliers, kept.error, kept.seconds)

    monkeypatch.setattr(pipeline, "optimize_batch", dropping)
    out = pipeline.run_isam(dataset, tmp_path / "isam", figures=False)
    assert out is not None
    assert out.report["outlier_factors"] == dropped
    # the settled estimate is the last batch optimum, which went without it
    for robot, poses in out.poses.items():
        for index, pose in poses.items():
            np.testing.assert_allclose(pose[:2], optimum[pose_key(robot, index)][:2], atol=1e-4)


def test_metrics_hold_the_gate_table_and_the_searches(dataset: Path, result: Path) -> None:
    metrics = evaluate(dataset)
    gate, mutual = metrics["mutual"]["gate"], metrics["mutual"]
    assert gate["accepted_true"] + gate["accepted_false"] == mutual["accepted"]
    assert gate["accepted_false"] == 0  # no distractor in essex_lab's simulated beacons
    assert sum(gate.values()) == mutual["events"]
    links = metrics["global_localization"]["link"]
    assert links["used"] >= 1
    assert links["used_max_m"] < 0.1
    assert links["used_max_deg"] < 1.0
    assert metrics["global_localization"]["validation"]["outside"] == []


def test_gate_table_counts_true_and_false_decisions() -> None:
    from estimation.app.evaluation.evaluate import _gate_table

    rows = [(0.01, 0.001, True), (0.5, 0.001, True), (0.01, 0.001, False), (2.0, 0.5, False),
            (float("nan"), float("nan"), False)]  # fmt: skip
    assert _gate_table(rows) == {"accepted_true": 1, "accepted_false": 1, "rejected_true": 1,
                                 "rejected_false": 1, "rejected_without_pose": 1}  # fmt: skip


def test_office_loop_closes_with_the_search_factors(tmp_path: Path) -> None:
    """The loop mission: station links and loop closures against the same data without them
    (``graph.search_factors: false``) — the issue's "at least 3× better" and the ATE figures."""
    data = tmp_path / "loop"
    run_simulation(REPO / "configs" / "missions" / "office_loop.yaml", data)
    run_batch(data, figures=False)
    run_batch(data, data / "without", overrides={"graph": {"search_factors": False}},
              figures=False)  # fmt: skip
    with_ = evaluate(data)
    without = evaluate(data, data / "without")
    searches = with_["global_localization"]
    assert searches["loop"]["used"] >= 1
    assert searches["loop"]["used_max_m"] < 0.1  # every loop closure: the paper's figure
    assert searches["loop"]["used_max_deg"] < 1.0
    # Station links: registered on the stations' points, all but a few within the paper's
    # figure. Two round corners of the corridor (their searches failed, the registration
    # seeded by odometry) are 10.8 and 20.9 cm off along the corridor at seed 0, the latter
    # with a sigma of 32 cm along it (design §7: the profile of the registration's cost).
    links = searches["link"]
    assert links["used_within_10cm_1deg"] >= 0.9 * links["used"]
    assert links["used_median_m"] < 0.02
    assert links["used_max_deg"] < 1.0
    report = json.loads((data / "result" / "report.json").read_text())
    used = [s for s in report["global_localization"]["searches"] if s["used"]]
    assert used
    assert min(s["overlap"] for s in used) >= 0.1
    assert without["global_localization"]["factors"] == 0
    for robot in ("a", "b"):
        ate, ate_without = with_["robots"][robot]["ate_m"], without["robots"][robot]["ate_m"]
        assert ate <= 0.02, ate  # 1.0 / 1.1 cm at seed 0
        assert with_["robots"][robot]["ate_deg"] < 0.2
        assert ate_without > 3 * ate, (ate, ate_without)  # ≈ 2.1 m without
    assert with_["map"]["precision"] > 0.9
    assert with_["map"]["recall"] > 0.9


def test_a_mission_without_mutual_observations_fails_in_one_line(
    dataset: Path, tmp_path: Path
) -> None:
    """Dwells without reference/mapper: robot b is tied to nothing; batch says so, exit 2."""
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy, ignore=shutil.ignore_patterns("result*"))
    events = [json.loads(line) for line in (copy / "events.jsonl").read_text().splitlines()]
    for event in events:
        event.pop("reference", None)
        event.pop("mapper", None)
    (copy / "events.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))
    result = CliRunner().invoke(app, ["batch", str(copy)])
    assert result.exit_code == 2
    assert result.stderr.strip().splitlines() == [
        "coopmap: error: robot b has no pose in the result: no mutual observation tied it to "
        f"the map (see unseen_pairs and missing_sweeps in {copy / 'result' / 'report.json'})"
    ]
    report = json.loads((copy / "result" / "report.json").read_text())
    assert report["observations"] == 0
    assert report["robots"]["a"]["poses"] == 3  # the gauge's own result is kept
