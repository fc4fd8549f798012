"""pytest configuration shared by test/unit and test/integration.

- Puts ``src/`` first on ``sys.path`` so the pure core imports without a built workspace, and
  ``test/unit`` (the shared helpers) last.
- Registers a Hypothesis profile without deadlines (a loaded CI machine must not turn slow
  examples into failures) and with derandomized example generation, so that runs are
  reproducible like everything else here; ``HYPOTHESIS_PROFILE=dev`` keeps random exploration.
- Fails the run loudly when nothing was collected: a test command that runs 0 tests must not
  look green.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SRC = str(REPO / "src")
if SRC not in sys.path:
    sys.path.insert(0, SRC)
# The shared helpers (helpers.py, fuzz_support.py) live in test/unit; integration tests use them too.
UNIT = str(REPO / "test" / "unit")
if UNIT not in sys.path:
    sys.path.append(UNIT)

try:
    from hypothesis import settings

    settings.register_profile("ci", deadline=None, derandomize=True, print_blob=True)
    settings.register_profile("dev", deadline=None)
    settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
except ImportError:  # hypothesis is optional for running a subset by hand
    pass


def pytest_collection_finish(session: pytest.Session) -> None:
    if not session.items and not session.config.option.collectonly:
        missing = [a for a in session.config.args if not Path(a.split("::")[0]).exists()]
        raise pytest.UsageError(
            f"no tests were collected from {' '.join(session.config.args)}"
            + (f" (not found: {' '.join(missing)})" if missing else ""))
