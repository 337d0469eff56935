"""The pose graph's structure: which poses the factors tie together (union–find over keys)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from estimation.errors import EstimationError
from estimation.posegraph.graph import FactorSpec
from estimation.posegraph.keys import key_label, split_key

__all__ = ["check_constrained", "connected"]


class _Components:
    """Disjoint sets of pose keys, joined by the factors between them (path halving)."""

    def __init__(self, keys: Iterable[int] = ()) -> None:
        self.parent = {k: k for k in keys}

    def find(self, k: int) -> int:
        parent = self.parent
        parent.setdefault(k, k)
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    def join(self, keys: Sequence[int]) -> None:
        root = self.find(keys[0])
        for k in keys[1:]:
            other = self.find(k)
            if other != root:
                self.parent[other] = root


def connected(factors: Iterable[FactorSpec], root: int) -> set[int]:
    """The keys that ``factors`` tie, directly or through others, to ``root``."""
    components = _Components()
    for f in factors:
        components.join(f.keys)
    top = components.find(root)
    return {k for k in components.parent if components.find(k) == top}


def check_constrained(factors: Sequence[FactorSpec], keys: Iterable[int]) -> None:
    """Raise ``EstimationError`` unless every pose is tied, through factors, to a prior.

    A robot whose poses are linked only to each other (odometry, no mutual observation or
    global localization) floats freely: the problem has no unique solution.
    """
    keys = list(keys)
    components = _Components(keys)
    anchored: set[int] = set()
    for spec in factors:
        for k in spec.keys:
            if k not in components.parent:
                raise EstimationError(f"{spec.describe()} refers to {key_label(k)}, not in values")
        if len(spec.keys) == 1:
            anchored.add(spec.keys[0])
        else:
            components.join(spec.keys)
    roots = {components.find(k) for k in anchored}
    loose: dict[str, list[int]] = {}
    for k in keys:
        if components.find(k) not in roots:
            robot, index = split_key(k)
            loose.setdefault(robot, []).append(index)
    if loose:
        parts = [
            f"robot {r} ({len(ix)} poses, {r}{min(ix)}…{r}{max(ix)})"
            for r, ix in sorted(loose.items())
        ]
        raise EstimationError(
            "unconstrained: " + ", ".join(parts) + " not connected to any prior; add a Start, a "
            "mutual observation or a global localization that ties them to the map"
        )
