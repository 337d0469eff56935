"""What every ``coopmap`` command shares: known errors as one line, the --config and --json options,
the console.

Known errors print one line on stderr and exit with code 2, never a traceback.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, ParamSpec, TypeVar

import typer
from rich.console import Console

from estimation.app.config import Config, ConfigError, load_config

__all__ = [
    "ConfigOption",
    "JsonOption",
    "check_seed",
    "cli_errors",
    "file_size",
    "make_console",
    "option_config",
]

P = ParamSpec("P")
R = TypeVar("R")

JsonOption = Annotated[
    bool, typer.Option("--json", help="Print one machine-readable JSON object on stdout.")
]

ConfigOption = Annotated[
    Path | None,
    typer.Option("--config", "-c", help="YAML file of overrides merged over the defaults."),
]

FiguresOption = Annotated[
    bool,
    typer.Option(
        "--figures/--no-figures",
        help="Draw the result's figures (figures/*.png); --no-figures saves a quarter of the time.",
    ),
]


def _known_errors() -> tuple[type[BaseException], ...]:
    from estimation.errors import EstimationError
    from mapping.errors import MapError
    from sensors.errors import SensorError

    return (ConfigError, SensorError, MapError, EstimationError, OSError)


def _describe(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror and exc.filename:
        return f"{exc.filename}: {exc.strerror.lower()}"
    return str(exc) or type(exc).__name__


def cli_errors(command: Callable[P, R]) -> Callable[P, R]:
    """Turn known errors into one line on stderr and exit code 2."""

    @functools.wraps(command)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return command(*args, **kwargs)
        except _known_errors() as exc:
            typer.echo(f"coopmap: error: {_describe(exc)}", err=True)
            raise typer.Exit(code=2) from None

    return wrapper


def option_overrides(path: Path | None) -> dict[str, Any] | None:
    """The --config file's YAML overrides (None without one); a bad file is a ConfigError."""
    from sensors.yamlio import read_yaml_mapping

    return read_yaml_mapping(path, ConfigError) if path is not None else None


def option_config(path: Path | None) -> Config:
    """The effective configuration: the defaults merged with the --config file, if any."""
    return load_config(path)


def check_seed(seed: int) -> None:
    """numpy's generators take non-negative seeds: a negative --seed is a known error."""
    if seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {seed}")


def make_console(stderr: bool = False) -> Console:
    """A console that never wraps long lines (paths) when the output is piped or captured."""
    return Console(stderr=stderr, highlight=False, soft_wrap=True)


def file_size(path: Path) -> str:
    """A file's size for people: ``12.3 MB`` or ``45 kB``."""
    size = path.stat().st_size
    return f"{size / 1e6:.1f} MB" if size >= 1e6 else f"{size / 1e3:.0f} kB"
