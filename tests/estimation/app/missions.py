"""Small simulated missions shared by the tests."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest


def copy_of(dataset: Path, factory: pytest.TempPathFactory, name: str) -> Path:
    """A copy of ``dataset`` (the session's ``essex_simulated``, say) in a fresh temporary
    folder named after ``name``."""
    return Path(shutil.copytree(dataset, factory.mktemp(name) / dataset.name))


#: essex_lab in one leapfrog step: robot a references, b takes one scan pose (73 s of mission,
#: two dwells), for tests that need a real dataset quickly.
ONE_STEP_MISSION = """\
world: essex_lab
seed: 0
robots:
  - {name: a, start: [2.0, 3.5, 20]}
  - {name: b, start: [3.5, 5.75, 220]}
plan:
  - {reference: a, mapper: b, scans: [[5.282, 6.053, -116.15]]}
"""
