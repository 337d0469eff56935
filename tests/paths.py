"""Where the tests find the repository and the shared real robot data (``../shared/data``)."""

from __future__ import annotations

from pathlib import Path

from estimation.app.resources import DATA_DIR

#: The repository root (the folder holding pyproject.toml).
REPO = Path(__file__).resolve().parents[1]
#: Real robot data beside the checkout; tests that need it skip, saying so, when it is absent.
DATA = DATA_DIR
