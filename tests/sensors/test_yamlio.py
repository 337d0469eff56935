"""Merging mappings: nested sections merge key by key, anything else is replaced."""

from __future__ import annotations

from sensors.yamlio import merge_mappings


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
