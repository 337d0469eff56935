"""Where the built-in configuration, worlds and missions live.

A source checkout (and an editable install) reads them from ``configs/`` at the repository root;
a wheel carries the same files as ``estimation/_configs``.
"""

from __future__ import annotations

from pathlib import Path

from estimation.app.config import ConfigError

__all__ = ["DATA_DIR", "builtin_names", "configs_dir", "resolve_builtin"]

_PACKAGE_DIR = Path(__file__).resolve().parents[1]  # estimation/
#: Real robot data (CARMEN logs, the FR079 OctoMap, g2o pose graphs) beside a source checkout:
#: ``../shared/data`` relative to the repository. Commands that read it take ``--data`` to point
#: elsewhere.
DATA_DIR = _PACKAGE_DIR.parent.parent / "shared" / "data"


def configs_dir() -> Path:
    """The folder holding ``default.yaml``, ``worlds/`` and ``missions/``."""
    for candidate in (_PACKAGE_DIR / "_configs", _PACKAGE_DIR.parent / "configs"):
        if (candidate / "default.yaml").is_file():
            return candidate
    raise ConfigError(f"built-in configs not found beside {_PACKAGE_DIR}; is coopmap installed?")


def builtin_names(kind: str) -> list[str]:
    """Names of the built-in files of one kind (``"worlds"`` or ``"missions"``)."""
    folder = configs_dir() / kind
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def resolve_builtin(kind: str, name_or_path: str | Path) -> Path:
    """A built-in name (``essex_lab``) or a path to a YAML file, as a path.

    An existing file wins over a built-in of the same name.
    """
    path = Path(name_or_path)
    if path.is_file() or path.suffix in (".yaml", ".yml") or len(path.parts) > 1:
        return path
    candidate = configs_dir() / kind / f"{name_or_path}.yaml"
    if candidate.is_file():
        return candidate
    known = ", ".join(builtin_names(kind)) or "none"
    singular = kind.rstrip("s")
    raise ConfigError(
        f"{str(name_or_path)!r} is neither a {singular} file nor a built-in {singular} "
        f"(built-in: {known})"
    )
