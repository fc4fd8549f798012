"""Fixtures shared by the unit tests: the package's ring and the simulated lab."""
from __future__ import annotations

from pathlib import Path

import pytest

from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.scene import Scene

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ring() -> CameraRing:
    """config/ring.yaml (a module may define its own ``ring``)."""
    return CameraRing.load(str(REPO / "config" / "ring.yaml"))


@pytest.fixture(scope="module")
def scene() -> Scene:
    """The default simulated lab."""
    return Scene.default()
