"""Loading YAML documents into validated pydantic models, with one-line error messages.

World files (``sensors.sim.world``) and configuration files (``estimation.app.config``) are both
YAML mappings validated by a pydantic schema. Errors name the file, the key path inside the
document and the offending value, e.g. ``grid.resolution_m: must be > 0 (got -0.1)``.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

__all__ = [
    "YAML_LIMIT_BYTES",
    "YAML_MAX_DEPTH",
    "format_validation_error",
    "merge_mappings",
    "parse_yaml",
    "read_file_bytes",
    "read_text_file",
    "read_yaml_mapping",
    "regular_file",
    "validate_mapping",
]

M = TypeVar("M", bound=BaseModel)

_MESSAGES = {
    "extra_forbidden": "unknown key",
    "missing": "required key is missing",
}


def _key_path(loc: tuple[int | str, ...]) -> str:
    parts: list[str] = []
    for item in loc:
        if isinstance(item, int):
            parts.append(f"[{item}]")
        else:
            parts.append(("." if parts else "") + item)
    return "".join(parts) or "(document)"


def _short_value(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def format_validation_error(exc: ValidationError, *, prefix: str = "") -> str:
    """One line naming each failing key path, the problem and the bad value."""
    items = []
    for err in exc.errors(include_url=False):
        # Errors raised inside model validators carry the model's own path; their message
        # names the fields involved.
        loc = tuple(part for part in err["loc"] if part != "__root__")
        message = _MESSAGES.get(err["type"], err["msg"])
        message = message.removeprefix("Value error, ")
        text = f"{_key_path(loc)}: {message}" if loc else message
        # Model-level checks name their values in the message; repeating the whole mapping
        # they were given would bury it.
        if err["type"] != "missing" and not isinstance(err["input"], dict):
            text += f" (got {_short_value(err['input'])})"
        items.append(text)
    return prefix + "; ".join(items)


def merge_mappings(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    """``top`` merged over ``base``: nested mappings merge key by key, anything else in ``top``
    replaces what ``base`` has. Neither argument is changed."""
    merged = dict(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merge_mappings(merged[key], value)
        else:
            merged[key] = value
    return merged


#: YAML documents coopmap reads (configs, worlds, missions, map metadata) are small.
YAML_LIMIT_BYTES = 16 * 2**20


def regular_file(path: Path | str, error: type[Exception]) -> os.stat_result:
    """The status of ``path`` if it is a regular file; else ``error``, one line.

    A FIFO, a device (``/dev/zero``) or a directory is refused before it is opened, so reading
    it never blocks and never fills memory.
    """
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc.strerror or exc}") from None
    if stat.S_ISDIR(info.st_mode):
        raise error(f"{path}: is a directory, expected a file") from None
    if not stat.S_ISREG(info.st_mode):
        raise error(f"{path}: not a regular file (a pipe or a device?)")
    return info


def read_file_bytes(path: Path | str, error: type[Exception], limit_bytes: int) -> bytes:
    """The bytes of a regular file (``regular_file``) of at most ``limit_bytes``; else ``error``."""
    path = Path(path)
    info = regular_file(path, error)
    if info.st_size > limit_bytes:
        raise error(f"{path}: {info.st_size:,} bytes, more than the {limit_bytes:,} expected")
    try:
        with path.open("rb") as handle:
            # read(n) reserves n bytes first: ask for what the file holds (and one byte more,
            # to notice a file that grew past the limit since it was measured).
            data = handle.read(min(limit_bytes, info.st_size) + 1)
            if info.st_size < len(data) <= limit_bytes:
                data += handle.read(limit_bytes + 1 - len(data))
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc.strerror or exc}") from None
    if len(data) > limit_bytes:
        raise error(f"{path}: more than the {limit_bytes:,} bytes expected")
    return data


def read_text_file(path: Path | str, error: type[Exception], limit_bytes: int) -> str:
    """The UTF-8 text of a regular file of at most ``limit_bytes`` (see ``read_file_bytes``)."""
    data = read_file_bytes(path, error, limit_bytes)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None


#: Deepest nesting of collections a YAML document may have; coopmap's files nest a few levels.
#: PyYAML's scanner slows quadratically with flow nesting, so a deep document is refused early.
YAML_MAX_DEPTH = 100


class _NoAliasLoader(yaml.SafeLoader):
    """PyYAML's safe loader without anchors and aliases: an alias bomb (a few hundred bytes that
    expand to gigabytes) is refused at its first alias, and a document nested deeper than
    ``YAML_MAX_DEPTH`` at its first node that deep."""

    _depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None, None, "aliases (*name) are not allowed", event.start_mark
            )
        if self._depth >= YAML_MAX_DEPTH:
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None, None, f"nested more than {YAML_MAX_DEPTH} levels deep", event.start_mark
            )
        self._depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def parse_yaml(text: str, source: str, error: type[Exception]) -> Any:
    """The document of ``text``; malformed YAML, aliases and absurd nesting are one-line errors."""
    try:
        return yaml.load(text, Loader=_NoAliasLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise error(f"{source}: malformed YAML{where}: {problem}") from None
    except RecursionError:
        raise error(f"{source}: YAML nested too deeply") from None


def read_yaml_mapping(path: Path, error: type[Exception]) -> dict[str, Any]:
    """Read a YAML file whose top level must be a mapping; raise ``error`` with one clear line.

    An empty file is an empty mapping.
    """
    text = read_text_file(path, error, YAML_LIMIT_BYTES)
    data = parse_yaml(text, str(path), error)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise error(f"{path}: expected a YAML mapping at the top level, got {type(data).__name__}")
    return data


def validate_mapping(
    model: type[M], data: dict[str, Any], error: type[Exception], source: str
) -> M:
    """Validate ``data`` against ``model``; raise ``error`` naming ``source`` and the key paths."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise error(format_validation_error(exc, prefix=f"{source}: ")) from None
