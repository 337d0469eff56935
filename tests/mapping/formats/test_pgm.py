"""Bands as ROS map_server maps (PGM + YAML): round trips, other writers' files, bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from mapping.band import Band
from mapping.errors import MapError
from mapping.formats import pgm
from mapping.formats.pgm import UNKNOWN_PIXEL, read_band_pgm, write_band_pgm
from tests.mapping.formats.map_server import load_map_server


def sample_band() -> Band:
    rng = np.random.default_rng(0)
    occupancy = rng.uniform(0, 1, (7, 11))
    occupancy[0, :4] = [0.0, 1.0, 1 / 3, 50 / 255]  # 50/255 → pixel 205, the unknown value
    known = rng.uniform(size=(7, 11)) > 0.2
    known[0, :4] = True
    return Band(np.where(known, occupancy, 0.0), known, np.array([-1.25, 3.5]), 0.05)


def test_round_trip_keeps_the_band_within_quantisation(tmp_path: Path) -> None:
    band = sample_band()
    pgm_path, yaml_path = write_band_pgm(tmp_path / "ceiling.yaml", band)
    assert pgm_path == tmp_path / "ceiling.pgm"
    back = read_band_pgm(yaml_path)
    np.testing.assert_array_equal(back.known, band.known)
    np.testing.assert_allclose(back.occupancy, band.occupancy, atol=1 / 255 + 1e-12)
    np.testing.assert_allclose(back.lower_xy, band.lower_xy)
    assert back.resolution_m == band.resolution_m
    assert back.occupancy[0, 1] == 1.0
    assert back.occupancy[0, 0] == 0.0


def test_files_follow_map_server(tmp_path: Path) -> None:
    band = sample_band()
    pgm_path, yaml_path = write_band_pgm(tmp_path / "ceiling.yaml", band)
    doc = yaml.safe_load(yaml_path.read_text())
    assert doc == {
        "image": "ceiling.pgm",
        "resolution": 0.05,
        "origin": [-1.25, 3.5, 0.0],
        "negate": 0,
        "occupied_thresh": 0.198,
        "free_thresh": 0.194,
        "mode": "trinary",
    }
    data = pgm_path.read_bytes()
    assert data.startswith(b"P5\n")
    pixels = np.frombuffer(data[-77:], np.uint8).reshape(7, 11)
    top = pixels[0]  # the image's first row is the band's last (largest y)
    assert top[0] == (
        UNKNOWN_PIXEL if not band.known[6, 0] else round(255 * (1 - band.occupancy[6, 0]))
    )
    bottom = pixels[-1]
    assert bottom[:4].tolist() == [255, 0, 170, UNKNOWN_PIXEL + 1]


def write_map(tmp_path: Path, header: bytes, pixels: bytes, **doc: object) -> Path:
    (tmp_path / "m.pgm").write_bytes(header + pixels)
    description = {"image": "m.pgm", "resolution": 0.1, "origin": [1.0, 2.0, 0.0]} | doc
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(description))
    return path


def test_reads_other_writers_headers_and_negate(tmp_path: Path) -> None:
    header = b"P5 # made by GIMP\n# another comment\n3\n2 255\n"
    path = write_map(tmp_path, header, bytes([0, 205, 255, 254, 100, 0]), negate=1)
    band = read_band_pgm(path)
    assert band.shape == (2, 3)
    np.testing.assert_array_equal(band.known, [[True, True, True], [True, False, True]])
    np.testing.assert_allclose(band.occupancy, [[254 / 255, 100 / 255, 0], [0, 0, 1]])
    np.testing.assert_allclose(band.lower_xy, [1.0, 2.0])


@pytest.mark.parametrize(
    ("header", "pixels", "doc", "message"),
    [
        (b"P2\n3 2\n255\n", b"0 0 0 0 0 0", {}, r"m.pgm: not a binary PGM \(P5\) image"),
        (b"P5\n3 2\n65535\n", bytes(12), {}, "only 8-bit PGM"),
        (b"P5\n3 2\n255\n", bytes(5), {}, r"truncated: 3 × 2 pixels need 6 bytes, found 5"),
        (b"P5\n3 x\n255\n", bytes(6), {}, "malformed PGM header"),
        (b"P5\n0 2\n255\n", b"", {}, r"empty image \(0 × 2\)"),
        (b"P5\n3 2\n255\n", bytes(6), {"resolution": -1}, "resolution must be positive"),
        (b"P5\n3 2\n255\n", bytes(6), {"resolution": "fine"}, "resolution must be a number"),
        (b"P5\n3 2\n255\n", bytes(6), {"origin": [1.0, 2.0]}, r"origin must be \[x, y, yaw\]"),
        (b"P5\n3 2\n255\n", bytes(6), {"origin": [1.0, 2.0, 0.5]}, "rotated map"),
        (b"P5\n3 2\n255\n", bytes(6), {"negate": 2}, "negate must be 0 or 1"),
        (b"P5\n3 2\n255\n", bytes(6), {"image": "absent.pgm"}, "absent.pgm: no such file"),
    ],
)
def test_bad_maps_are_clear_errors(
    tmp_path: Path, header: bytes, pixels: bytes, doc: dict, message: str
) -> None:
    with pytest.raises(MapError, match=message):
        read_band_pgm(write_map(tmp_path, header, pixels, **doc))


def test_bad_descriptions_are_clear_errors(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("image: [unclosed\n")
    with pytest.raises(MapError, match=r"bad\.yaml: malformed YAML"):
        read_band_pgm(path)
    path.write_text("- a list\n")
    with pytest.raises(MapError, match="must be a YAML mapping"):
        read_band_pgm(path)
    path.write_text("image: m.pgm\nresolution: 0.1\n")
    with pytest.raises(MapError, match="missing key 'origin'"):
        read_band_pgm(path)
    with pytest.raises(MapError, match=r"absent\.yaml: no such file"):
        read_band_pgm(tmp_path / "absent.yaml")
    with pytest.raises(MapError, match=r"must be a \.yaml file"):
        write_band_pgm(tmp_path / "map.png", sample_band())


def test_map_server_loads_unknown_free_and_occupied(tmp_path: Path) -> None:
    band = sample_band()
    _, yaml_path = write_band_pgm(tmp_path / "ceiling.yaml", band)
    cells, _ = load_map_server(yaml_path)
    assert cells.shape == band.shape
    # Every known pixel lands on one side of the unknown pixel's occupancy (50/255).
    expected = np.where(band.occupancy > 50.5 / 255, 100, 0)
    np.testing.assert_array_equal(cells, np.where(band.known, expected, -1))
    assert cells[0, :4].tolist() == [0, 100, 100, 0]  # 50/255 is written as 206: free
    assert set(np.unique(cells).tolist()) == {-1, 0, 100}


def test_the_loader_follows_the_scale_and_negate_rules(tmp_path: Path) -> None:
    band = sample_band()
    _, yaml_path = write_band_pgm(tmp_path / "ceiling.yaml", band)
    doc = yaml.safe_load(yaml_path.read_text())
    # What the file said before: scale mode reads 205 as a known, nearly free cell.
    (tmp_path / "scale.yaml").write_text(yaml.safe_dump(
        {**doc, "mode": "scale", "occupied_thresh": 0.65, "free_thresh": 0.196}))  # fmt: skip
    scale, _ = load_map_server(tmp_path / "scale.yaml")
    assert scale[~band.known].tolist() == [0] * int((~band.known).sum())
    assert scale[0, 2] == round((1 / 3 - 0.196) / (0.65 - 0.196) * 100)
    (tmp_path / "negate.yaml").write_text(yaml.safe_dump({**doc, "negate": 1}))
    negated, _ = load_map_server(tmp_path / "negate.yaml")
    assert negated[0, :2].tolist() == [100, 0]  # white reads as occupied


def test_a_failed_write_keeps_the_old_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _, yaml_path = write_band_pgm(tmp_path / "ceiling.yaml", sample_band())
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def crash(path: Path, text: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(pgm, "write_text_atomic", crash)
    with pytest.raises(OSError, match="disk full"):
        write_band_pgm(yaml_path, sample_band())
    assert (tmp_path / "ceiling.yaml").read_bytes() == before["ceiling.yaml"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ceiling.pgm", "ceiling.yaml"]


def test_absurd_headers_pipes_and_aliases_are_clear_errors(tmp_path: Path) -> None:
    import os

    (tmp_path / "map.yaml").write_text("image: map.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n")
    (tmp_path / "map.pgm").write_bytes(b"P5\n" + b"9" * 5000 + b" 2\n255\n" + bytes(6))
    with pytest.raises(MapError, match=r"map\.pgm: PGM header number of 5000 digits"):
        read_band_pgm(tmp_path / "map.yaml")
    (tmp_path / "map.pgm").unlink()
    os.mkfifo(tmp_path / "map.pgm")
    with pytest.raises(MapError, match=r"map\.pgm: not a regular file"):
        read_band_pgm(tmp_path / "map.yaml")  # returns at once: the FIFO is never opened
    (tmp_path / "alias.yaml").write_text("a: &a [1, 2]\nimage: *a\n")
    with pytest.raises(MapError, match=r"alias\.yaml: malformed YAML .*aliases"):
        read_band_pgm(tmp_path / "alias.yaml")
