import numpy as np
import pytest

from estimation.errors import EstimationError
from estimation.posegraph.graph import FactorSpec
from estimation.posegraph.keys import pose_key
from estimation.posegraph.structure import check_constrained, connected


def factor(kind: str, *labels: tuple[str, int]) -> FactorSpec:
    return FactorSpec(kind, tuple(pose_key(*label) for label in labels),  # type: ignore[arg-type]
                      np.zeros(3), np.eye(3) * 0.01, 0)  # fmt: skip


def two_robots_and_a_third_apart() -> list[FactorSpec]:
    """a0 (prior) – a1 by odometry, a1 – b0 by a mutual observation, b0 – b1; c0 – c1 – c2
    by odometry only."""
    return [
        factor("prior", ("a", 0)),
        factor("odometry", ("a", 0), ("a", 1)),
        factor("mutual", ("a", 1), ("b", 0)),
        factor("odometry", ("b", 0), ("b", 1)),
        factor("odometry", ("c", 0), ("c", 1)),
        factor("odometry", ("c", 1), ("c", 2)),
    ]


def keys(*labels: str) -> set[int]:
    return {pose_key(label[0], int(label[1:])) for label in labels}


def test_connected_keys_are_those_tied_to_the_root() -> None:
    factors = two_robots_and_a_third_apart()
    assert connected(factors, pose_key("a", 0)) == keys("a0", "a1", "b0", "b1")
    assert connected(factors, pose_key("c", 2)) == keys("c0", "c1", "c2")
    assert connected([], pose_key("a", 0)) == keys("a0")  # a root no factor holds is alone
    # A global factor between stations joins the components.
    joined = [*factors, factor("global", ("b", 1), ("c", 0))]
    assert connected(joined, pose_key("a", 0)) == keys("a0", "a1", "b0", "b1", "c0", "c1", "c2")


def test_unconstrained_robot_is_named() -> None:
    factors = two_robots_and_a_third_apart()
    every = keys("a0", "a1", "b0", "b1", "c0", "c1", "c2")
    with pytest.raises(
        EstimationError, match=r"unconstrained: robot c \(3 poses, c0…c2\) not connected"
    ):
        check_constrained(factors, every)
    # Without the mutual observation, b floats too.
    no_mutual = [f for f in factors if f.kind != "mutual"]
    with pytest.raises(EstimationError, match=r"robot b \(2 poses, b0…b1\), robot c"):
        check_constrained(no_mutual, every)
    with pytest.raises(EstimationError, match="refers to c5, not in values"):
        check_constrained([factor("prior", ("c", 5))], [])
    check_constrained([*factors, factor("global", ("c", 0))], every)  # a prior on c: all tied
