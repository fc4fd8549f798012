"""tracker.py: the pipeline on simulated frames: follows a moving robot, recovers from a kidnap,
resets on a bag loop."""
from __future__ import annotations

import numpy as np
import pytest

from aruco_ring_localization import geometry as geo
from aruco_ring_localization.ring import CameraRing
from aruco_ring_localization.simulation.ring_sim import RingSimulator, perturb_ring
from aruco_ring_localization.simulation.scene import Scene
from aruco_ring_localization.tracker import RingTracker

from helpers import RING_YAML


@pytest.fixture(scope="module")
def setup():
    scene = Scene.default()
    ring = CameraRing.load(str(RING_YAML))
    sim = RingSimulator(scene, perturb_ring(ring, seed=1), pixel_noise=0.3, seed=2)
    return scene, ring, sim


def _pose(t):
    return np.array([4.5 + 0.2 * t, 4.0 + 0.1 * t, geo.wrap_angle(0.3 * t)])


def test_follows_then_recovers_from_kidnap_then_resets_on_time_jump(setup):
    scene, ring, sim = setup
    tracker = RingTracker(ring, scene.truth_map())
    for k in range(30):
        t = 0.1 * k
        truth = _pose(t)
        tracker.set_motion("cmd_vel", 0.22, 0.3, t)
        out = tracker.process(sim.observe(scene.T_world_base(truth), t))
        err = np.hypot(*(out.pose[:2] - truth[:2]))
        assert err < 0.03, f"t={t:.1f}: tracking error {err * 100:.2f} cm"
    # Kidnap: the robot is carried 1.5 m away and stops.
    kidnapped = np.array([6.0, 5.0, 1.0])
    reasons = []
    for k in range(30, 45):
        out = tracker.process(sim.observe(scene.T_world_base(kidnapped), 0.1 * k))
        reasons.append(out.decision.reason)
    assert "jump" in reasons and "reinitialized" in reasons, f"gate decisions after the kidnap: {reasons}"
    assert np.hypot(*(out.pose[:2] - kidnapped[:2])) < 0.02, f"not recovered: {out.pose}"
    # Bag loop: time goes back to 0.
    out = tracker.process(sim.observe(scene.T_world_base(_pose(0.0)), 0.0))
    assert out.time_jump and tracker.time_jumps == 1
    assert np.hypot(*(out.pose[:2] - _pose(0.0)[:2])) < 0.02, f"after the time jump: {out.pose}"


def test_no_markers_predicts_only(setup):
    scene, ring, sim = setup
    tracker = RingTracker(ring, scene.truth_map())
    T = scene.T_world_base(_pose(0.0))
    tracker.process(sim.observe(T, 0.0))
    c0 = np.trace(tracker.filter.covariance)
    empty = sim.observe(T, 0.5)
    for f in empty.cameras.values():
        f.observations.clear()
    out = tracker.process(empty)
    assert out.decision is None and not out.localization.ok
    assert np.trace(out.covariance) > c0
