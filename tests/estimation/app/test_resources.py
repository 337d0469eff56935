"""Finding the built-in configuration, worlds and missions."""

from __future__ import annotations

from pathlib import Path

import pytest

from estimation.app import resources
from estimation.app.config import ConfigError
from tests.paths import REPO


def test_source_tree_layout() -> None:
    assert resources.configs_dir() == REPO / "configs"
    assert resources.builtin_names("worlds") == ["cluttered_hall", "essex_lab", "office_loop"]
    assert (
        resources.resolve_builtin("worlds", "essex_lab") == REPO / "configs/worlds/essex_lab.yaml"
    )


def test_wheel_layout_is_preferred(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    package = tmp_path / "estimation"
    (package / "_configs" / "worlds").mkdir(parents=True)
    (package / "_configs" / "default.yaml").write_text("{}\n")
    (package / "_configs" / "worlds" / "hall.yaml").write_text("name: hall\n")
    monkeypatch.setattr(resources, "_PACKAGE_DIR", package)
    assert resources.configs_dir() == package / "_configs"
    assert resources.builtin_names("worlds") == ["hall"]
    assert resources.builtin_names("missions") == []


def test_missing_configs_is_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(resources, "_PACKAGE_DIR", tmp_path / "estimation")
    with pytest.raises(ConfigError, match="built-in configs not found"):
        resources.configs_dir()


def test_paths_pass_through_and_unknown_names_fail(tmp_path: Path) -> None:
    world = tmp_path / "mine.yaml"
    assert resources.resolve_builtin("worlds", world) == world  # a path, existing or not
    assert resources.resolve_builtin("worlds", "sub/dir/w") == Path("sub/dir/w")
    with pytest.raises(
        ConfigError, match=r"'atlantis' is neither a world file nor a built-in world"
    ):
        resources.resolve_builtin("worlds", "atlantis")
