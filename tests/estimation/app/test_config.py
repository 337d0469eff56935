"""The configuration schema: defaults file, merging, and every rejection path."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml

from estimation.app.config import (
    BandConfig,
    Config,
    ConfigError,
    config_from_mapping,
    config_to_yaml,
    load_config,
)
from tests.paths import REPO

DEFAULT_YAML = REPO / "configs" / "default.yaml"


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "override.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_default_yaml_equals_schema_defaults() -> None:
    on_disk = yaml.safe_load(DEFAULT_YAML.read_text(encoding="utf-8"))
    assert on_disk == Config().model_dump(mode="json")


def test_default_yaml_lists_every_section() -> None:
    on_disk = yaml.safe_load(DEFAULT_YAML.read_text(encoding="utf-8"))
    assert list(on_disk) == [
        "scanner", "mirror", "beacon", "robot", "grid", "bands", "search", "graph",
        "simulation", "serial",
    ]  # fmt: skip


def test_load_default_file_gives_defaults() -> None:
    assert load_config(DEFAULT_YAML) == Config()
    assert load_config(None) == Config()


def test_effective_config_round_trips_through_yaml(tmp_path: Path) -> None:
    changed = config_from_mapping({"grid": {"resolution_m": 0.05}, "search": {"window_m": 6.0}})
    path = write(tmp_path, config_to_yaml(changed))
    assert load_config(path) == changed


def test_override_merges_over_defaults(tmp_path: Path) -> None:
    cfg = load_config(
        write(tmp_path, "grid:\n  resolution_m: 0.05\nbands:\n  ceiling: {min_m: 2.4}\n")
    )
    assert cfg.grid.resolution_m == 0.05
    assert cfg.grid.prob_hit == Config().grid.prob_hit  # untouched key in the same section
    assert cfg.bands.ceiling == BandConfig(min_m=2.4, max_m=2.9)  # max_m kept from the defaults
    assert cfg.bands.floor == Config().bands.floor
    assert cfg.scanner == Config().scanner


def test_empty_override_file_gives_defaults(tmp_path: Path) -> None:
    assert load_config(write(tmp_path, "")) == Config()


def test_degrees_in_files_are_radians_in_code(tmp_path: Path) -> None:
    cfg = load_config(
        write(tmp_path, "beacon: {blind_wedge_deg: 30}\ngraph: {beacon_bearing_sigma_deg: 0.5}\n")
    )
    assert cfg.beacon.blind_wedge_rad == pytest.approx(math.pi / 6, abs=1e-15)
    assert cfg.graph.beacon_bearing_sigma_rad == pytest.approx(math.radians(0.5), abs=1e-15)
    assert cfg.mirror.motor_rate_hz == pytest.approx(2.0)


def test_integers_are_accepted_for_floats(tmp_path: Path) -> None:
    assert load_config(write(tmp_path, "mirror: {period_s: 40}\n")).mirror.period_s == 40.0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("scanner:\n  foo: 3\n", r"scanner\.foo: unknown key \(got 3\)"),
        ("nonsense_section: {a: 1}\n", r"nonsense_section: unknown key"),
        ("grid: {resolution_m: '0.1'}\n", r"grid\.resolution_m: Input should be a valid number \(got '0\.1'\)"),
        ("grid: {resolution_m: -0.1}\n", r"grid\.resolution_m: Input should be greater than or equal to 0\.005 \(got -0\.1\)"),
        ("grid: {resolution_m: 0.0005}\n", r"grid\.resolution_m: Input should be greater than or equal to 0\.005 \(got 0\.0005\)"),
        ("grid: {resolution_m: 0}\n", r"grid\.resolution_m: Input should be greater than or equal to 0\.005 \(got 0\)"),
        ("grid: {resolution_m: .nan}\n", r"grid\.resolution_m: Input should be a finite number \(got nan\)"),
        ("grid: {block_size_cells: 16.5}\n", r"grid\.block_size_cells: Input should be a valid integer \(got 16\.5\)"),
        ("grid: 5\n", r"grid: Input should be a valid dictionary"),
        ("bands: {ceiling: {min_m: 3.0, max_m: 2.0}}\n", r"bands\.ceiling: min_m \(3\.0\) must be below max_m \(2\.0\)"),
        ("bands: {floor: {min_m: 1.0, max_m: 1.0}}\n", r"bands\.floor: min_m \(1\.0\) must be below max_m \(1\.0\)"),
        ("scanner: {angular_resolution_deg: 0.3}\n", r"scanner\.angular_resolution_deg: must be one of 1, 0\.5, 0\.25 \(got 0\.3\)"),
        ("scanner: {field_of_view_deg: 120}\n", r"scanner\.field_of_view_deg: Input should be 100 or 180 \(got 120\)"),
        ("scanner: {field_of_view_deg: 180, angular_resolution_deg: 0.25}\n", r"scanner: the LMS 200 has no 180° variant at 0\.25°"),
        ("scanner: {measuring_mode: 7}\n", r"scanner\.measuring_mode: must be an LMS 200 measuring mode"),
        ("grid: {prob_hit: 0.4}\n", r"grid\.prob_hit: Input should be greater than 0\.5 \(got 0\.4\)"),
        ("grid: {clamp_min: 0.6}\n", r"grid: need clamp_min < occupied_threshold < clamp_max"),
        ("serial: {baud_rate: 115200}\n", r"serial\.baud_rate: Input should be 9600, 19200, 38400 or 500000 \(got 115200\)"),
        ("serial: {password: short}\n", r"serial\.password: String should have at least 8 characters \(got 'short'\)"),
        ("serial: {permanent_baud: 1}\n", r"serial\.permanent_baud: Input should be a valid boolean \(got 1\)"),
        ("graph: {robust: tukey}\n", r"graph\.robust: Input should be 'gnc_tls', 'huber', 'cauchy' or 'none' \(got 'tukey'\)"),
        ("search: {station_beta: 0}\n", r"search\.station_beta: Input should be greater than 0 \(got 0\)"),
        ("search: {score: ncc}\n", r"search\.score: Input should be 'agreement', 'centred' or 'excess' \(got 'ncc'\)"),
        ("bands: {free_min_observed: 1.5}\n", r"bands\.free_min_observed: Input should be less than or equal to 1 \(got 1\.5\)"),
        ("search: {window_m: 50.0}\n", r"search: window_m \(50\.0\) must not exceed max_window_m \(40\.0\)"),
        ("mirror: {elevation_min_deg: 10, elevation_max_deg: 0}\n", r"mirror: elevation_min_deg \(10\.0\) must be below"),
        ("beacon: {height_m: 0.4}\n", r"beacon \(height_m 0\.4, length_m 0\.6\) must sit above the scanner"),
    ],
)  # fmt: skip
def test_rejections_name_the_key_and_value(tmp_path: Path, text: str, message: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError, match=message) as info:
        load_config(path)
    assert str(info.value).startswith(f"{path}: ")
    assert "\n" not in str(info.value)


def test_several_errors_are_all_reported(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, "grid: {resolution_m: -1, foo: 2}\n"))
    assert "grid.resolution_m" in str(info.value)
    assert "grid.foo: unknown key" in str(info.value)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("grid: {resolution_m: [\n", r"malformed YAML at line \d+, column \d+"),
        ("- 1\n- 2\n", r"expected a YAML mapping at the top level, got list"),
        ("just a string\n", r"expected a YAML mapping at the top level, got str"),
    ],
)
def test_malformed_files_are_rejected(tmp_path: Path, text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        load_config(write(tmp_path, text))


def test_missing_file_and_directory_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"missing\.yaml: no such file"):
        load_config(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match=r"is a directory"):
        load_config(tmp_path)


def test_binary_garbage_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "garbage.yaml"
    path.write_bytes(b"\xff\xfe\x00\x81garbage")
    with pytest.raises(ConfigError, match=r"garbage\.yaml: not UTF-8 text"):
        load_config(path)


def test_config_is_frozen() -> None:
    cfg = Config()
    with pytest.raises(ValueError, match="frozen"):
        cfg.grid.resolution_m = 0.2  # type: ignore[misc]


def test_station_searches_use_station_beta(tmp_path: Path) -> None:
    from estimation.app.rig import station_params

    config = load_config(write(tmp_path, "search: {beta: 0.05, station_beta: 0.2}\n"))
    params = station_params(config)
    assert params.search.beta == pytest.approx(0.05)
    assert params.station_search.beta == pytest.approx(0.2)
    assert params.station_search.free_weight == params.search.free_weight


def test_the_search_score_reaches_every_search(tmp_path: Path) -> None:
    from estimation.app.rig import station_params

    params = station_params(load_config(write(tmp_path, "search: {score: centred}\n")))
    assert params.search.metric.score == params.station_search.metric.score == "centred"
    assert station_params(Config()).search.metric.score == "agreement"


def test_the_grid_resolution_bound_is_the_grids_own() -> None:
    """The schema repeats the bound (importing mapping.grid would load numba for --help)."""
    from mapping.grid import MIN_RESOLUTION_M

    field = Config.model_fields["grid"].annotation.model_fields["resolution_m"]  # type: ignore[union-attr]
    assert [m.ge for m in field.metadata if hasattr(m, "ge")] == [MIN_RESOLUTION_M]
