"""Shared fixtures: the essex_lab mission simulated once per test session.

Eight test modules need a small real dataset of their own to read, damage or write results
into. Simulating essex_lab takes about 5 s; the simulation is deterministic, so each module
gets a copy of the one made for the session instead of simulating again.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.paths import REPO


@pytest.fixture(scope="session")
def essex_simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """essex_lab as ``coopmap simulate`` writes it (no result); never modified: copy it."""
    from estimation.app.sim.simulate import run_simulation

    out = tmp_path_factory.mktemp("essex_session") / "essex"
    run_simulation(REPO / "configs" / "missions" / "essex_lab.yaml", out)
    return out
