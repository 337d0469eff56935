"""numba's cache folder per state of the kernels' sources (sensors.jitcache)."""

from __future__ import annotations

import os
from pathlib import Path

import numba.core.config
import pytest

from sensors import jitcache


def _tree(root: Path) -> None:
    for package in ("estimation", "mapping", "sensors"):
        (root / package / "__pycache__").mkdir(parents=True)
    (root / "mapping" / "kernel.py").write_text("from numba import njit\n")
    (root / "sensors" / "helper.py").write_text("def helper():\n    return 1\n")
    (root / "estimation" / "__pycache__" / "kernel.py").write_text("import numba  # a copy\n")


def test_the_key_follows_the_files_that_use_numba_only(tmp_path: Path) -> None:
    _tree(tmp_path)
    first = jitcache.source_key(tmp_path)
    assert len(first) == 16
    (tmp_path / "sensors" / "helper.py").write_text("def helper():\n    return 2\n")
    (tmp_path / "estimation" / "__pycache__" / "kernel.py").write_text("import numba  # other\n")
    assert jitcache.source_key(tmp_path) == first  # no numba there, or not a source folder
    (tmp_path / "mapping" / "kernel.py").write_text("from numba import njit  # changed\n")
    changed = jitcache.source_key(tmp_path)
    assert changed != first
    (tmp_path / "mapping" / "other.py").write_text("import numba\n")
    assert jitcache.source_key(tmp_path) not in (first, changed)


@pytest.fixture
def isolated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A source tree and a cache home of its own; numba's setting restored afterwards."""
    _tree(tmp_path / "src")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setattr(numba.core.config, "CACHE_DIR", numba.core.config.CACHE_DIR)
    return tmp_path


def test_the_cache_folder_is_the_sources_states_and_old_ones_go(isolated: Path) -> None:
    home = isolated / "cache" / "coopmap" / "numba"
    home.mkdir(parents=True)
    old = [home / f"{k:016x}" for k in range(5)]
    for n, folder in enumerate(old):
        folder.mkdir()
        os.utime(folder, (1_000_000 + n, 1_000_000 + n))
    keep = [home / "notes.txt", home / "not-a-key"]
    keep[0].write_text("the user's\n")
    keep[1].mkdir()
    folder = jitcache.key_numba_cache(isolated / "src")
    assert folder == home / jitcache.source_key(isolated / "src")
    assert folder.is_dir()
    assert os.environ["NUMBA_CACHE_DIR"] == str(folder)
    assert str(folder) == numba.core.config.CACHE_DIR
    # This state's folder and the two newest before it stay; only coopmap's names are removed.
    assert sorted(p.name for p in home.iterdir() if p.is_dir()) == sorted(
        [folder.name, old[4].name, old[3].name, "not-a-key"]
    )
    assert keep[0].read_text() == "the user's\n"


def test_a_numba_cache_dir_the_user_set_is_left_alone(
    isolated: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(isolated / "mine"))
    assert jitcache.key_numba_cache(isolated / "src") is None
    assert os.environ["NUMBA_CACHE_DIR"] == str(isolated / "mine")
    assert not (isolated / "cache").exists()


def test_an_unwritable_cache_home_leaves_numbas_default(
    isolated: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (isolated / "cache").write_text("a file where the folder would be\n")
    assert jitcache.key_numba_cache(isolated / "src") is None
    assert "NUMBA_CACHE_DIR" not in os.environ
