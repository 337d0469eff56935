"""Small simulated missions shared by the tests."""

from __future__ import annotations

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
