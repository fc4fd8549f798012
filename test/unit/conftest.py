"""Fixtures shared by the unit tests: the package's ring, the simulated lab, its true map and
frames of it."""
from __future__ import annotations

from pathlib import Path

import pytest

from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.ring_sim import RingSimulator
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


@pytest.fixture(scope="module")
def truth(scene):
    """The lab's true marker map (a module may define its own ``truth``)."""
    return scene.truth_map()


@pytest.fixture(scope="module")
def frames(ring, scene):
    """6 frames at each of the lab's mapping stations, 0.3 px noise, seeded (a module may define
    its own ``frames``)."""
    sim = RingSimulator(scene, ring, pixel_noise=0.3, seed=2)
    return [sim.observe(Scene.T_world_base(p), stamp=10.0 * k + 0.1 * i)
            for k, p in enumerate(scene.mapping_stations) for i in range(6)]
