"""A result's figures: the ceiling band tells unknown from free, one measured sweep (paper
Fig. 4b), the search PDFs as surfaces (Fig. 5b), and which searches a result draws."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from estimation.app.figures import _block_max, render_search_pdf, render_sweep, render_trajectories
from estimation.app.results import MAX_PDF_FIGURES, _pdf_figures
from estimation.search.records import SearchPicture, SearchRecord, records_json
from mapping.band import Band
from mapping.figures import UNKNOWN_COLOR

PNG = b"\x89PNG\r\n\x1a\n"


def _band() -> Band:
    """A 40 × 60 cell band: the left half observed free, the right half unknown, a wall across."""
    occupancy = np.zeros((40, 60))
    known = np.zeros((40, 60), dtype=bool)
    known[:, :30] = True
    occupancy[20, :30] = 1.0
    return Band(occupancy, known, np.array([0.0, 0.0]), 0.1)


def _rgb(path: Path) -> np.ndarray:
    return np.asarray(imread(path))[..., :3].reshape(-1, 3)


def _share_of(rgb: np.ndarray, color: tuple[float, float, float]) -> float:
    return float((np.abs(rgb - np.array(color)).max(axis=1) < 0.02).mean())


def test_the_ceiling_figure_draws_unknown_apart_from_free(tmp_path: Path) -> None:
    path = render_trajectories(_band(), {"a": {0: np.array([1.0, 1.0, 0.0])}}, tmp_path / "c.png")
    rgb = _rgb(path)
    unknown = tuple(int(UNKNOWN_COLOR[i : i + 2], 16) / 255 for i in (1, 3, 5))
    # Both halves of the band cover a visible share of the figure, in different colours.
    assert _share_of(rgb, unknown) > 0.05
    assert _share_of(rgb, (1.0, 1.0, 1.0)) > 0.05


def test_a_sweep_is_drawn_coloured_by_distance_and_skips_bad_points(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    points = rng.uniform(-5, 5, (5000, 3))
    points[::50] = np.nan
    path = render_sweep(points, tmp_path / "s.png", beacons=np.array([[1.0, 2.0, 0.5]]),
                        max_points=1000)  # fmt: skip
    assert path.read_bytes()[:8] == PNG
    rgb = _rgb(path)
    # turbo colours: many distinct hues, not one marker colour
    assert len(np.unique((rgb * 8).astype(int), axis=0)) > 40
    empty = render_sweep(np.zeros((0, 3)), tmp_path / "empty.png")
    assert empty.read_bytes()[:8] == PNG


def _picture() -> SearchPicture:
    x_m = np.linspace(0.0, 3.0, 31)
    y_m = np.linspace(0.0, 2.0, 21)
    gx, gy = np.meshgrid(x_m, y_m)
    marginal = np.exp(-((gx - 1.5) ** 2 + (gy - 1.0) ** 2) / 0.02).astype(np.float32)
    return SearchPicture(x_m, y_m, marginal / marginal.sum(), _band(), _band())


def test_a_search_pdf_is_drawn_as_a_surface_beside_the_map(tmp_path: Path) -> None:
    path = render_search_pdf(_picture(), np.array([1.5, 1.0, 0.3]), tmp_path / "p.png",
                             title="loop closure")  # fmt: skip
    assert path.read_bytes()[:8] == PNG
    assert imread(path).shape[1] > imread(path).shape[0]  # two panels side by side


def _record(kind: str, station: str, used: bool, t: float, picture: bool = True) -> SearchRecord:
    return SearchRecord(
        station=station, against="map" if kind == "relocalize" else "a0", kind=kind,
        band="ceiling", pose=(0.0, 0.0, 0.0), peak_ratio=10.0, dominant=True, used=used,
        seconds=0.1, time_s=t, overlap=0.5, picture=_picture() if picture else None,
    )  # fmt: skip


def test_relocalizations_then_used_loop_closures_are_drawn_up_to_the_cap() -> None:
    records = [_record("loop", f"a{n}", used=n % 2 == 0, t=float(n)) for n in range(20)]
    records += [_record("relocalize", "b9", used=False, t=99.0)]
    records += [_record("link", "a3", used=True, t=3.0, picture=False)]
    drawn = _pdf_figures(records)
    assert len(drawn) == MAX_PDF_FIGURES
    assert drawn[0][0] == "pdf_relocalization_b9_map_ceiling.png"
    kinds = [(r.kind, r.used) for _, r in drawn]
    assert kinds[1:] == [("loop", True)] * (MAX_PDF_FIGURES - 1)  # used loop closures first
    floor = [_record("relocalize", "a1", used=False, t=1.0)]
    floor = [SearchRecord(**{**floor[0].__dict__, "band": "floor"})]
    assert _pdf_figures(floor) == []  # the floor band's relocalizations are not drawn
    assert len({name for name, _ in drawn}) == len(drawn)


def test_a_pictures_pdf_sums_to_one_and_stays_out_of_the_report() -> None:
    from estimation.search.exhaustive import SearchParams, search

    band = _band()
    result = search(band, band, SearchParams(angular_resolution_rad=math.radians(10.0)))
    picture = SearchPicture.of(result, band, band)
    assert picture.marginal.shape == (len(result.y_m), len(result.x_m))
    assert picture.marginal.sum() == pytest.approx(1.0, abs=1e-4)
    row = records_json([_record("loop", "a5", used=True, t=1.0)])[0]
    assert "picture" not in row
    assert row["station"] == "a5"


def test_the_pdf_surface_keeps_a_one_position_peak_when_it_is_coarsened() -> None:
    values = np.zeros((301, 250))
    values[137, 91] = 1.0  # a peak one position wide that a stride of 6 would step over
    coarse = _block_max(values, 6, 5)
    assert coarse.shape == (51, 50)
    assert coarse[137 // 6, 91 // 5] == 1.0
    assert np.count_nonzero(coarse) == 1
    assert _block_max(values, 1, 1) is values
    assert _block_max(np.zeros((0, 0)), 3, 3).size == 0
