"""``coopmap localize`` on map_server files, and ``coopmap bench search``'s report."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from estimation.app.cli.main import app
from estimation.search.scenes import local_view, random_building, rasterise
from mapping.formats.pgm import write_band_pgm

TRUTH = (6.23, 9.71, -57.3)  # x_m, y_m, yaw_deg of the scan grid's frame in the map frame


def run(*args: str) -> tuple[int, str, str]:
    result = CliRunner().invoke(app, list(args))
    return result.exit_code, result.stdout, result.stderr


def assert_one_line_error(code: int, stderr: str, pattern: str) -> None:
    assert code == 2
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("coopmap: error: ")
    assert re.search(pattern, lines[0]), lines[0]


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("localize")
    rng = np.random.default_rng(3)
    scene = random_building(rng, 12.0)
    band = rasterise(scene, np.zeros(3), (-1.0, -1.0), (140, 140), 0.1)
    write_band_pgm(folder / "map.yaml", band)
    truth = np.array([TRUTH[0] - 1.0, TRUTH[1] - 1.5, math.radians(TRUTH[2])])
    scan = local_view(scene, truth, 5.0, 0.1, rng, noise=0.1, drop_fraction=0.2)
    write_band_pgm(folder / "scan.yaml", scan)
    return folder / "map.yaml", folder / "scan.yaml"


def truth_in_map() -> np.ndarray:
    # The scene was drawn with its origin at the map's (0, 0): the truth above, shifted back.
    return np.array([TRUTH[0] - 1.0, TRUTH[1] - 1.5, TRUTH[2]])


def test_localize_json_reports_the_pose_of_the_scan_frame(files: tuple[Path, Path]) -> None:
    map_yaml, scan_yaml = files
    code, stdout, stderr = run(
        "localize", "--map", str(map_yaml), "--scan", str(scan_yaml), "--json"
    )
    assert code == 0, stderr
    report = json.loads(stdout)
    assert {"x_m", "y_m", "yaw_deg", "cov", "peak_ratio", "seconds"} <= set(report)
    x, y, yaw = truth_in_map()
    assert report["x_m"] == pytest.approx(x, abs=0.05)
    assert report["y_m"] == pytest.approx(y, abs=0.05)
    assert math.remainder(report["yaw_deg"] - yaw, 360.0) == pytest.approx(0.0, abs=0.5)
    cov = np.array(report["cov"])
    assert cov.shape == (3, 3)
    assert np.allclose(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert report["peak_ratio"] is None or report["peak_ratio"] > 100
    assert report["dominant"] is True
    assert report["windows_m"] == []
    assert report["poses_searched"] == 140 * 140 * 360
    assert 0 < report["seconds"] < 60


def test_localize_with_a_prior_grows_a_window(files: tuple[Path, Path]) -> None:
    map_yaml, scan_yaml = files
    x, y, _ = truth_in_map()
    code, stdout, stderr = run(
        "localize", "--map", str(map_yaml), "--scan", str(scan_yaml),
        "--prior", f"{x + 1.3}", f"{y - 0.9}", "0", "--window-m", "1", "--json",
    )  # fmt: skip
    assert code == 0, stderr
    report = json.loads(stdout)
    assert report["windows_m"][:2] == [1.0, 2.0]
    assert len(report["windows_m"]) >= 3
    assert report["poses_searched"] < 140 * 140 * 360
    assert report["x_m"] == pytest.approx(x, abs=0.05)
    assert report["y_m"] == pytest.approx(y, abs=0.05)


def test_localize_text_and_pdf_figure(files: tuple[Path, Path], tmp_path: Path) -> None:
    map_yaml, scan_yaml = files
    figure = tmp_path / "pdf.png"
    code, stdout, stderr = run(
        "localize", "--map", str(map_yaml), "--scan", str(scan_yaml), "--pdf-out", str(figure)
    )
    assert code == 0, stderr
    assert stdout.startswith("coopmap localize: x=")
    assert "dominant" in stdout
    assert f"wrote {figure}" in stdout
    from matplotlib.image import imread

    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = np.asarray(imread(figure))
    assert image.shape[1] > 1000
    assert len(np.unique((image[..., :3].reshape(-1, 3) * 255).astype(np.uint8), axis=0)) > 50


def test_unreadable_pgm_is_one_line_error(files: tuple[Path, Path], tmp_path: Path) -> None:
    map_yaml, _ = files
    bad = tmp_path / "bad.yaml"
    bad.write_text("image: bad.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n", encoding="utf-8")
    (tmp_path / "bad.pgm").write_bytes(b"P2\n3 3\n255\n1 2 3\n")
    code, _, stderr = run("localize", "--map", str(map_yaml), "--scan", str(bad))
    assert_one_line_error(code, stderr, r"bad\.pgm: not a binary PGM")
    code, _, stderr = run("localize", "--map", str(tmp_path / "missing.yaml"), "--scan", str(bad))
    assert_one_line_error(code, stderr, "missing.yaml: no such file")


def test_mismatched_resolution_is_one_line_error(files: tuple[Path, Path], tmp_path: Path) -> None:
    map_yaml, scan_yaml = files
    text = scan_yaml.read_text(encoding="utf-8").replace("resolution: 0.1", "resolution: 0.05")
    other = tmp_path / "scan05.yaml"
    other.write_text(text.replace("image: scan.pgm", f"image: {scan_yaml.with_suffix('.pgm')}"))
    code, _, stderr = run("localize", "--map", str(map_yaml), "--scan", str(other))
    assert_one_line_error(code, stderr, r"resolution 0\.05 m differs from the map's 0\.1 m")


def test_empty_scan_grid_is_one_line_error(files: tuple[Path, Path], tmp_path: Path) -> None:
    map_yaml, _ = files
    (tmp_path / "empty.pgm").write_bytes(b"P5\n4 4\n255\n" + bytes([205] * 16))
    (tmp_path / "empty.yaml").write_text(
        "image: empty.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n", encoding="utf-8"
    )
    code, _, stderr = run(
        "localize", "--map", str(map_yaml), "--scan", str(tmp_path / "empty.yaml")
    )
    assert_one_line_error(code, stderr, "scan grid has no known cell")


def test_window_outside_the_map_and_window_without_prior(files: tuple[Path, Path]) -> None:
    map_yaml, scan_yaml = files
    base = ("localize", "--map", str(map_yaml), "--scan", str(scan_yaml))
    code, _, stderr = run(*base, "--prior", "80", "80", "0", "--window-m", "4")
    assert_one_line_error(code, stderr, "lies outside the map")
    code, _, stderr = run(*base, "--window-m", "4")
    assert_one_line_error(code, stderr, "--window-m needs --prior")
    code, _, stderr = run(*base, "--pdf-out", "figure.jpg")
    assert_one_line_error(code, stderr, "must name a .png file")


def test_a_map_too_large_to_search_whole_is_one_line_within_bounded_memory(
    tmp_path: Path,
) -> None:
    """An 8,000 × 8,000 map_server map (64 MB): 23 G poses, beyond even the coarse-to-fine
    search's lattice (the whole PDF would need 86 GiB of scores)."""
    import tracemalloc

    n = 8000
    image = np.full((n, n), 205, np.uint8)
    image[::50] = 0
    (tmp_path / "map.pgm").write_bytes(b"P5\n%d %d\n255\n" % (n, n) + image.tobytes())
    description = "resolution: 0.05\norigin: [0, 0, 0]\nnegate: 0\n"
    (tmp_path / "map.yaml").write_text("image: map.pgm\n" + description)
    (tmp_path / "scan.pgm").write_bytes(b"P5\n80 80\n255\n" + image[:80, :80].tobytes())
    (tmp_path / "scan.yaml").write_text("image: scan.pgm\n" + description)
    del image
    tracemalloc.start()
    code, _, err = run(
        "localize", "--map", str(tmp_path / "map.yaml"), "--scan", str(tmp_path / "scan.yaml")
    )
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert_one_line_error(
        code, err, r"would cover 23,040,000,000 poses \(8000 × 8000 positions × 360 headings\); "
        r"at most 2,147,483,648 are searched coarse to fine: search a window around a prior"
    )  # fmt: skip
    assert peak < 0.9e9  # the file (64 MB), the band (512 + 64 MB), a mask (64 MB)


def test_a_map_beyond_the_whole_pdf_is_localized_coarse_to_fine(tmp_path: Path) -> None:
    """88 m × 88 m at 0.1 m and 1°: 279 M poses, more than the whole PDF holds (2^28). A 24 m
    office floor lies in it; the rest of the map is unknown."""
    from estimation.search.scenes import office_floor
    from mapping.band import Band

    rng = np.random.default_rng(5)
    scene = office_floor(rng, 24.0)
    part = rasterise(scene, np.zeros(3), (0.0, 0.0), (240, 240), 0.1)
    n, at = 880, 300
    occupancy, known = np.zeros((n, n)), np.zeros((n, n), dtype=bool)
    occupancy[at : at + 240, at : at + 240] = part.occupancy
    known[at : at + 240, at : at + 240] = part.known
    write_band_pgm(tmp_path / "map.yaml", Band(occupancy=occupancy, known=known,
                                              lower_xy=np.zeros(2), resolution_m=0.1))  # fmt: skip
    truth = np.array([11.3, 13.9, math.radians(121.0)])
    scan = local_view(scene, truth, 8.0, 0.1, rng, noise=0.1, drop_fraction=0.2)
    write_band_pgm(tmp_path / "scan.yaml", scan)
    args = ("localize", "--map", str(tmp_path / "map.yaml"), "--scan", str(tmp_path / "scan.yaml"))
    code, stdout, stderr = run(*args, "--json")
    assert code == 0, stderr
    report = json.loads(stdout)
    assert report["poses_searched"] == 880 * 880 * 360
    assert report["poses_at_full_resolution"] < 0.01 * report["poses_searched"]
    assert 0 <= report["unevaluated_mass"] < 1e-5
    assert report["x_m"] == pytest.approx(truth[0] + 30.0, abs=0.05)
    assert report["y_m"] == pytest.approx(truth[1] + 30.0, abs=0.05)
    assert math.remainder(report["yaw_deg"] - 121.0, 360.0) == pytest.approx(0.0, abs=0.5)
    assert report["dominant"] is True
    code, stdout, stderr = run(*args, "--pdf-out", str(tmp_path / "pdf.png"))
    assert code == 0, stderr
    assert re.search(
        r"coarse to fine: [\d,]+ at full resolution, estimated unevaluated mass ", stdout
    )
    assert (tmp_path / "pdf.png").stat().st_size > 10_000
