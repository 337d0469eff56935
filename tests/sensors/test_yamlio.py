"""Merging mappings: nested sections merge key by key, anything else is replaced."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from sensors.yamlio import merge_mappings, parse_yaml, read_text_file, read_yaml_mapping


def test_nested_mappings_merge_key_by_key() -> None:
    base = {"grid": {"resolution_m": 0.1, "clamp": {"min": 0.12}}, "seed": 0, "robots": ["a"]}
    top = {"grid": {"clamp": {"max": 0.97}}, "robots": ["b", "c"]}
    merged = merge_mappings(base, top)
    assert merged == {
        "grid": {"resolution_m": 0.1, "clamp": {"min": 0.12, "max": 0.97}},
        "seed": 0,
        "robots": ["b", "c"],
    }
    assert base["grid"] == {"resolution_m": 0.1, "clamp": {"min": 0.12}}  # untouched
    assert top == {"grid": {"clamp": {"max": 0.97}}, "robots": ["b", "c"]}


def test_a_scalar_replaces_a_section_and_a_section_replaces_a_scalar() -> None:
    assert merge_mappings({"grid": {"resolution_m": 0.1}}, {"grid": None}) == {"grid": None}
    assert merge_mappings({"grid": 3}, {"grid": {"a": 1}}) == {"grid": {"a": 1}}
    assert merge_mappings({}, {}) == {}


def test_pipes_devices_and_huge_files_are_refused_before_reading(tmp_path: Path) -> None:
    fifo = tmp_path / "config.yaml"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match=r"config\.yaml: not a regular file"):
        read_yaml_mapping(fifo, ValueError)  # returns at once: a FIFO is never opened
    with pytest.raises(ValueError, match=r"/dev/zero: not a regular file"):
        read_yaml_mapping(Path("/dev/zero"), ValueError)
    big = tmp_path / "big.yaml"
    big.write_bytes(b"a: 1\n" + b"#" * 200)
    with pytest.raises(ValueError, match=r"big\.yaml: 205 bytes, more than the 100 expected"):
        read_text_file(big, ValueError, 100)
    with pytest.raises(ValueError, match=r"absent\.yaml: no such file"):
        read_yaml_mapping(tmp_path / "absent.yaml", ValueError)


def test_alias_bombs_and_deep_nesting_are_one_line_errors(tmp_path: Path) -> None:
    bomb = tmp_path / "bomb.yaml"
    lines = ['a: &a ["x", "x", "x", "x", "x", "x", "x", "x", "x"]']
    lines += [f"{chr(98 + k)}: &{chr(98 + k)} [*{chr(97 + k)}, *{chr(97 + k)}, *{chr(97 + k)}]"
              for k in range(8)]  # fmt: skip
    bomb.write_text("\n".join(lines) + "\n")
    started = time.perf_counter()
    with pytest.raises(ValueError, match=r"bomb\.yaml: malformed YAML at line 2.*aliases"):
        read_yaml_mapping(bomb, ValueError)
    assert time.perf_counter() - started < 1.0
    deep = tmp_path / "deep.yaml"
    deep.write_text("a: " + "[" * 20000 + "]" * 20000 + "\n")
    with pytest.raises(ValueError, match=r"deep\.yaml: (YAML nested too deeply|malformed YAML)"):
        read_yaml_mapping(deep, ValueError)


def test_parse_yaml_keeps_plain_documents() -> None:
    assert parse_yaml("a: {b: [1, 2.5, x]}\n", "doc", ValueError) == {"a": {"b": [1, 2.5, "x"]}}
    assert parse_yaml("", "doc", ValueError) is None
